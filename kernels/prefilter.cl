/* Stage 1: integer Gaussian prefilter (paper section 4) and the column sums of the
 * summed-area table. One work item walks down a strip of 16 columns: it computes the
 * horizontal pass of the row RADIUS below (reads clamped to the frame, rounded to gray
 * levels) into a sliding window of 2 RADIUS + 1 rows held in registers, the vertical pass
 * of the current row from that window (no round trip through memory), and the running
 * column sums (uint16 arithmetic wraps; every box sum taken from the table
 * is below 2^16, so box sums stay exact).
 * With COMPENSATE, each strip also stores its pixel sum of P (brightness compensation).
 * The taps are symmetric (w[i] == w[2 RADIUS - i]): mirror pairs are added first and
 * multiplied once. Sums stay below 2^16 (255 * 256 + 128), so ushort lanes are exact. */

__constant ushort PF_W[2 * RADIUS + 1] = { WEIGHTS };

/* 128 + sum_i w[i] * src[i * step - RADIUS * step], 16 lanes (src at the centre tap) */
#define TAPS16(acc, src, step)                                                          \
    do {                                                                                \
        acc = (ushort16)(128) + PF_W[RADIUS] * convert_ushort16(LOAD_UC16(src));       \
        _Pragma("unroll") for (int i_ = 0; i_ < RADIUS; i_++)                           \
            acc += PF_W[i_] * (convert_ushort16(LOAD_UC16((src) - (RADIUS - i_) * (step))) \
                               + convert_ushort16(LOAD_UC16((src) + (RADIUS - i_) * (step)))); \
    } while (0)

inline ushort16 horizontal16(__global const uchar *row, int x0)
{
    ushort16 acc;
    if (x0 >= RADIUS && x0 + 15 + RADIUS <= W - 1) {
        TAPS16(acc, row + x0, 1);
    } else {
        /* frame edge: copy the clamped reads, then the same vector taps */
        uchar ext[16 + 2 * RADIUS + 16];
        for (int j = 0; j < 16 + 2 * RADIUS; j++)
            ext[j] = row[CLAMPI(x0 + j - RADIUS, 0, W - 1)];
        const uchar *c = ext + RADIUS;
        /* packed-struct loads: vload16 is a library call on PoCL */
#define LOAD_PRIV16(p) convert_ushort16(((const uchar16_u *)(p))->v)
        acc = (ushort16)(128) + PF_W[RADIUS] * LOAD_PRIV16(c);
        _Pragma("unroll") for (int i = 0; i < RADIUS; i++)
            acc += PF_W[i] * (LOAD_PRIV16(c - (RADIUS - i)) + LOAD_PRIV16(c + (RADIUS - i)));
    }
    return acc >> 8;
}

__kernel void prefilter_columns(__global const uchar *frame, __global uchar *P, __global ushort *sat,
                                __global char *result, int slot, int p_slot, __global uint *bright)
{
    /* first, zero this work item's share of the frame's counters and histograms (the later
     * stages add to them atomically): cheaper than a separate fill command */
    {
        __global int *stats = (__global int *)(result + STATS_OFFSET);
        const int n = (int)get_global_size(0), share = (N_STATS + n - 1) / n;
        const int first = (int)get_global_id(0) * share;
        const int last = first + share < N_STATS ? first + share : N_STATS;
        for (int j = first; j < last; j++) stats[j] = 0;
    }
    const int x0 = get_global_id(0) * 16;
    if (x0 >= W) return;  /* the global size is padded to whole work-groups */
    __global ushort *S = sat + slot * SAT_SIZE + SPAD + 1 + x0;
    __global uchar *Pout = P + p_slot * P_SIZE + PPAD + x0;
    /* the horizontal passes of rows y - RADIUS .. y + RADIUS (clamped to the frame) in a
     * window of registers that slides down one row per step (constant indices only),
     * kept in 16-bit lanes: narrowing each row to bytes and widening it again for the
     * vertical pass cost ~13 % of this kernel (shuffle-port work) */
    ushort16 h[2 * RADIUS + 1];
    _Pragma("unroll") for (int j = 0; j < 2 * RADIUS + 1; j++)
        h[j] = horizontal16(frame + CLAMPI(j - RADIUS, 0, H - 1) * W, x0);
    ushort16 colsum = (ushort16)(0);
#if COMPENSATE
    /* the strip's pixel sum, from the wrapping column sums every 256 rows (a difference
     * of at most 256 * 255 < 2^16 is exact in ushort): no per-row cost */
    ushort16 mark = (ushort16)(0);
    uint8 sum_lo = (uint8)(0), sum_hi = (uint8)(0);  /* 256-bit vectors only (see common.cl) */
#endif
    for (int y = 0; y < H; y++) {
        ushort16 acc = (ushort16)(128) + PF_W[RADIUS] * h[RADIUS];
        _Pragma("unroll") for (int j = 0; j < RADIUS; j++)
            acc += PF_W[j] * (h[j] + h[2 * RADIUS - j]);
        const ushort16 p = acc >> 8;
        /* lanes beyond W fall in padding that nothing reads unmasked */
        STORE_UC16(Pout + y * PSTRIDE, convert_uchar16(p));
        colsum += p;
        STORE_US16(S + (y + 1) * SSTRIDE, colsum);
#if COMPENSATE
        if ((y & 255) == 255 || y == H - 1) {
            const ushort16 rows = colsum - mark;
            sum_lo += convert_uint8(rows.lo);
            sum_hi += convert_uint8(rows.hi);
            mark = colsum;
        }
#endif
        _Pragma("unroll") for (int j = 0; j < 2 * RADIUS; j++) h[j] = h[j + 1];
        /* past the last row the window repeats it (clamped reads): no pass to recompute */
        if (y + RADIUS + 1 < H)
            h[2 * RADIUS] = horizontal16(frame + (y + RADIUS + 1) * W, x0);
    }
#if COMPENSATE
    /* lanes past W hold clamped copies: not part of the frame */
    const int8 lane = (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    sum_lo &= as_uint8(lane < (W - x0));
    sum_hi &= as_uint8(lane < (W - x0 - 8));
    const uint8 s8 = sum_lo + sum_hi;
    const uint4 s4 = s8.lo + s8.hi;
    bright[P_SLOTS + p_slot * NSTRIPS + x0 / 16] = s4.x + s4.y + s4.z + s4.w;
#endif
}
