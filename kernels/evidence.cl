/* The summary's evidence, binned by the detector kernel (evd.cl) on every
 * EVIDENCE_ROW_STEP-th row (and in the columns set in the EVIDENCE_COLUMNS word mask) right
 * after it has fused the row's detections: each detection
 * by (axis, signed channel, orientation of the gradient of the receptor image R_k at the
 * middle receptor B at t - D) and by position. */

/* |table| <= 2^14 and |g| < 2^16 (box sums of an 8-bit image, k <= 15), so the cross
 * products below fit in 32 bits */
__constant int OC[NBINS - 1] = { ORIENT_C };
__constant int OS[NBINS - 1] = { ORIENT_S };

__attribute__((always_inline)) inline int box_at(__global const ushort *S, int cx, int cy, int r)
{
    __global const ushort *top = S + (cy - r) * SSTRIDE + SPAD + cx - r;
    __global const ushort *bot = S + (cy + r + 1) * SSTRIDE + SPAD + cx - r;
    const int w = 2 * r + 1;
    return (ushort)(bot[w] - top[w] - bot[0] + top[0]);  /* exact below 2^16 */
}

/* 1 when the gradient lies at or beyond boundary b (the exact integer test) */
#define BEYOND(b) (OC[(b)] * gy - OS[(b)] * gx >= 0)

/* The bin is the number of boundaries b with OC[b] gy - OS[b] gx >= 0 (gradient folded
 * into the upper half-plane). The boundaries are sorted by angle, so the test is true for
 * b < bin and false after: a branch-free binary search finds the exact count in
 * log2(NBINS) steps (a float arctangent guess cost twice as much on PoCL). */
#if (NBINS & (NBINS - 1)) != 0
#error "the orientation search needs a power-of-two bin count"
#endif

__attribute__((always_inline)) inline int orientation_bin(int gx, int gy)
{
    const int flip = -((gy < 0) | ((gy == 0) & (gx < 0)));
    gx = (gx ^ flip) - flip;
    gy = (gy ^ flip) - flip;
    int n = 0;
#pragma unroll
    for (int step = NBINS / 2; step >= 1; step >>= 1) {
        const int b = n + step - 1;
        n += (b < NBINS - 1 && BEYOND(b)) ? step : 0;
    }
    return n;
}

/* Run-length counting: neighbouring detections along an edge often fall in the same bin,
 * so each run of equal bins is flushed with one atomic add. */
typedef struct { int bin, len; } bin_run;

__attribute__((always_inline)) inline void run_count(__global int *counts, bin_run *run, int bin)
{
    if (bin != run->bin) {
        if (run->len) ATOMIC_ADD(counts + run->bin, run->len);
        run->bin = bin;
        run->len = 0;
    }
    run->len++;
}

__attribute__((always_inline)) inline void run_flush(__global int *counts, bin_run *run)
{
    if (run->len) ATOMIC_ADD(counts + run->bin, run->len);
    run->bin = -1;
    run->len = 0;
}

/* Bin the detections of word i of row y (bit planes b0..b3 = channel index c + 1, bs =
 * sign) of one axis into the position and orientation histograms. */
inline void bin_detections(__global int *positions, __global int *hist, __global const ushort *sat, int t,
                           int axis, int y, int i, uint b0, uint b1, uint b2, uint b3, uint bs,
                           bin_run *pos_run, bin_run *hist_run)
{
    uint any = (b0 | b1 | b2 | b3) & EVIDENCE_COLUMNS;
    while (any) {
        const uint l = (uint)__builtin_ctz(any);
        any &= any - 1;
        const int x = i * 32 + (int)l;
        const int c = (int)(((b0 >> l) & 1u) | (((b1 >> l) & 1u) << 1) | (((b2 >> l) & 1u) << 2)
                            | (((b3 >> l) & 1u) << 3)) - 1;
        const int negative = (int)((bs >> l) & 1u);
        const int where = axis ? y * POS_BINS / H : x * POS_BINS / W;
        run_count(positions, pos_run, ((axis * 2 * NCH) + 2 * c + negative) * POS_BINS + where);
        const int k = CK[c], r = k / 2, D = CD[c];
        __global const ushort *S = sat + pos_mod(t - D, SAT_SLOTS) * SAT_SIZE;
        const int step = negative ? -k : k;
        const int bx = axis ? x : x + step;
        const int by = axis ? y + step : y;
        const int xr = bx + 1 < W - 1 - r ? bx + 1 : W - 1 - r;
        const int xl = bx - 1 > r ? bx - 1 : r;
        const int yd = by + 1 < H - 1 - r ? by + 1 : H - 1 - r;
        const int yu = by - 1 > r ? by - 1 : r;
        const int gx = box_at(S, xr, by, r) - box_at(S, xl, by, r);
        const int gy = box_at(S, bx, yd, r) - box_at(S, bx, yu, r);
        if (gx == 0 && gy == 0) continue;
        run_count(hist, hist_run, (axis * 2 * NCH + 2 * c + negative) * NBINS + orientation_bin(gx, gy));
    }
}
