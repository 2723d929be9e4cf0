/* Stage 4 (last): Elementary Velocity Detectors (paper section 3) and fusion, bit-sliced.
 * One work item per run of 8 consecutive words of the state planes (up to 256 pixels, one
 * uint8 vector per bit plane); every template test is a few bitwise operations on whole
 * vectors. The planes' rows are read as one flat sequence of words: a row's NW words
 * follow the zero word that separates it from the previous row, so a run may cross a row
 * end and no work is spent on padding to whole vectors per row (at 640 px: 21 words a row
 * instead of 24). Zero rows above and below and the zero words between rows mean nothing
 * tests bounds, and a lane on a separating word never fires (it has no states).
 *
 * For channel (k, D), direction delta and pixel A = x: B = x + k delta, C = x + 2k delta;
 * the velocity template fires when the same (polarity, type) motion template matches
 * A->B on the states at (t-2D, t-D) and B->C on the states at (t-D, t).
 * Fusion: the fastest channel that fires wins; both directions at that channel =
 * ambiguous (no output). Output per axis: five bit planes, the winning channel index
 * c + 1 (4 bits) and the sign; the host turns them into int8 codes +-(c+1) only when the
 * dense field is read. On every EVIDENCE_ROW_STEP-th row the detections are also binned
 * for the summary (evidence.cl): one launch less, and the fused planes are binned
 * straight from the registers.
 * The axes are fused one after the other: the fusion state of one axis (6 vectors) plus
 * the template operands fit the 16 AVX2 registers; both axes at once spilled.
 * With DIAGONAL, runs that hold an evidence row also run the detectors along the two
 * diagonals (B = A + k (1, 1) and A + k (1, -1)) and bin their fused detections on that
 * row as histogram axes 2 and 3: they feed the summary only, not the output planes. */

/* bits of pixels x0 + j + s, j = 0..31, for 0 < |s| < 32, for 8 words at once */
inline uint8 along(__global const uint *p, int s)
{
    return s > 0 ? (LOAD_W8(p) >> (uint)s) | (LOAD_W8(p + 1) << (uint)(32 - s))
                 : (LOAD_W8(p) << (uint)(-s)) | (LOAD_W8(p - 1) >> (uint)(32 + s));
}

inline uint8 at(__global const uint *p, int dy, int dx)
{
    return dx == 0 ? LOAD_W8(p + dy * NWP) : along(p + dy * NWP, dx);
}

inline uint lane_popcount(uint8 v)
{
    return POPCOUNT(v.s0) + POPCOUNT(v.s1) + POPCOUNT(v.s2) + POPCOUNT(v.s3)
         + POPCOUNT(v.s4) + POPCOUNT(v.s5) + POPCOUNT(v.s6) + POPCOUNT(v.s7);
}

/* velocity template matches of channel c at the pixels of the run from flat word f (row
 * f / NWP, word f % NWP - 1 of that row), for the direction (dx, dy) in units of k */
__attribute__((always_inline)) inline uint8 matches(__global const uint *planes, int c, int t, int f, int ux, int uy)
{
    const int k = CK[c], D = CD[c], L = CRING[c], base = CBASE[c];
    const int s0 = base + pos_mod(t - 2 * D, L), s1 = base + pos_mod(t - D, L), s2 = base + t % L;
    f -= 1;  /* flat word 0 is row 0's leading zero word */
    __global const uint *P0 = planes + PLANE_ROW(s0, 0, 0) + f, *N0 = planes + PLANE_ROW(s0, 1, 0) + f;
    __global const uint *P1 = planes + PLANE_ROW(s1, 0, 0) + f, *N1 = planes + PLANE_ROW(s1, 1, 0) + f;
    __global const uint *P2 = planes + PLANE_ROW(s2, 0, 0) + f, *N2 = planes + PLANE_ROW(s2, 1, 0) + f;
    const int dx = ux * k, dy = uy * k;
    const uint8 pa0 = LOAD_W8(P0), na0 = LOAD_W8(N0), pa1 = LOAD_W8(P1), na1 = LOAD_W8(N1);
    const uint8 pb0 = at(P0, dy, dx), nb0 = at(N0, dy, dx);
    const uint8 pb1 = at(P1, dy, dx), nb1 = at(N1, dy, dx);
    const uint8 pb2 = at(P2, dy, dx), nb2 = at(N2, dy, dx);
    const uint8 pc1 = at(P1, 2 * dy, 2 * dx), nc1 = at(N1, 2 * dy, 2 * dx);
    const uint8 pc2 = at(P2, 2 * dy, 2 * dx), nc2 = at(N2, 2 * dy, 2 * dx);
    /* z..: no state (za1 = A empty at t-D, zb0 = B empty at t-2D, ...) */
    const uint8 za1 = ~(pa1 | na1), zb0 = ~(pb0 | nb0), zb2 = ~(pb2 | nb2), zc1 = ~(pc1 | nc1);
    /* per polarity: A and B, C share it; start [p 0 / p p] and end [p p / 0 p] on both
     * links, factored: start = a0 & ~b0 & a1 & b1 & ~c1 & b2 & c2, end = a0 & b0 & ~a1 &
     * b1 & c1 & ~b2 & c2 */
    const uint8 pcom = pa0 & pb1 & pc2, ncom = na0 & nb1 & nc2;
    const uint8 start = zb0 & zc1, end = za1 & zb2;
    uint8 fired = (pcom & ((start & pa1 & pb2) | (end & pb0 & pc1)))
                | (ncom & ((start & na1 & nb2) | (end & nb0 & nc1)));
#if SHARP
    /* sharp [p 0 / 0 p] on both links */
    fired |= (pcom | ncom) & zb0 & za1 & zc1 & zb2;
#endif
    return fired;
}

/* Fusion of channel c's matches mp (positive direction) and mn (negative), channels taken
 * from the fastest down: where no faster channel fired, c wins where exactly one direction
 * fired (both = ambiguous: no output), its index c + 1 goes into the bit planes idx0..idx3
 * and the sign plane; either direction marks the pixel decided. A macro, not a function:
 * the same text in both loops, and the compiler keeps every plane in a register (a helper
 * taking them by pointer measured 8-10 % slower). */
#define FUSE_CHANNEL(c, mp, mn)                                              \
    do {                                                                     \
        const uint8 p_ = (mp) & ~decided, n_ = (mn) & ~decided, won_ = p_ ^ n_; \
        sign |= n_ & ~p_;                                                    \
        if (((c) + 1) & 1) idx0 |= won_;                                     \
        if (((c) + 1) & 2) idx1 |= won_;                                     \
        if (((c) + 1) & 4) idx2 |= won_;                                     \
        if (((c) + 1) & 8) idx3 |= won_;                                     \
        decided |= (mp) | (mn);                                              \
    } while (0)

__kernel void velocity_detectors(__global const uint *planes, __global char *result,
                                 __global uint *debug, __global const ushort *sat, __global const uchar *P, int t,
                                 int theta_q, __global const uint *bright, __global const int *theta_tiles)
{
    const int f = get_global_id(0) * 8;   /* first flat word of the run */
    if (f >= H * NWP) return;  /* the global size is padded to whole work-groups */
    __global int *stats = (__global int *)(result + STATS_OFFSET);
    /* this work-group's copy of the counters (common.cl) */
    __global int *counters = stats + (get_group_id(0) % COUNTER_COPIES) * SLOT_INTS;
    __global uint *out = (__global uint *)result + f;
    /* does the run hold a row whose detections feed the summary's evidence? */
    const int y_first = f / NWP, y_last = (f + 7) / NWP;
    const int evidence_row = (y_first + EVIDENCE_ROW_STEP - 1) / EVIDENCE_ROW_STEP * EVIDENCE_ROW_STEP;
    const bool evidence = EVIDENCE && evidence_row <= y_last && evidence_row < H;

    for (int axis = 0; axis < 2; axis++) {
        uint8 decided = (uint8)(0u), sign = (uint8)(0u);
        uint8 idx0 = decided, idx1 = decided, idx2 = decided, idx3 = decided;
#pragma unroll
        for (int c = NCH - 1; c >= 0; c--) {
            /* E, W along the row; S, N k rows away */
            const uint8 mp = axis ? matches(planes, c, t, f, 0, 1) : matches(planes, c, t, f, 1, 0);
            const uint8 mn = axis ? matches(planes, c, t, f, 0, -1) : matches(planes, c, t, f, -1, 0);
#ifdef DEBUG_MATCHES
            STORE_W8(debug + (c * 4 + 2 * axis) * OUT_PLANE + f, mp);
            STORE_W8(debug + (c * 4 + 2 * axis + 1) * OUT_PLANE + f, mn);
#endif
            FUSE_CHANNEL(c, mp, mn);
        }
        /* planes (axis, bit, flat word) */
        __global uint *o = out + axis * 5 * OUT_PLANE;
        const uint8 any = idx0 | idx1 | idx2 | idx3;
        STORE_W8(o, idx0);
        STORE_W8(o + OUT_PLANE, idx1);
        STORE_W8(o + 2 * OUT_PLANE, idx2);
        STORE_W8(o + 3 * OUT_PLANE, idx3);
        STORE_W8(o + 4 * OUT_PLANE, sign);   /* set only where a channel won */
        const uint count = lane_popcount(any);
        if (count) ATOMIC_ADD(counters + (axis ? STAT_V : STAT_U), (int)count);
        if (count && evidence) {
            /* the summary's evidence (evidence.cl), straight from the fused planes.
             * Copies of the histograms, one per work-group index modulo their count: the
             * CPU threads then rarely increment the same cache line (the host adds them up) */
            bin_evidence(stats + STAT_POS + (get_group_id(0) % POS_COPIES) * POS_SIZE,
                         stats + STAT_HIST + (get_group_id(0) % HIST_COPIES) * HIST_SIZE, sat, P, bright, t,
                         theta_q, theta_tiles, axis, f, idx0, idx1, idx2, idx3, sign);
        }
    }
#if DIAGONAL
    if (!evidence) return;
    for (int axis = 2; axis < 4; axis++) {
        const int uy = axis == 2 ? 1 : -1;
        uint8 decided = (uint8)(0u), sign = (uint8)(0u);
        uint8 idx0 = decided, idx1 = decided, idx2 = decided, idx3 = decided;
#pragma unroll
        for (int c = NCH - 1; c >= 0; c--) {
            const uint8 mp = matches(planes, c, t, f, 1, uy), mn = matches(planes, c, t, f, -1, -uy);
            FUSE_CHANNEL(c, mp, mn);
        }
        bin_evidence(0, stats + STAT_HIST + (get_group_id(0) % HIST_COPIES) * HIST_SIZE, sat, P, bright, t,
                     theta_q, theta_tiles, axis, f, idx0, idx1, idx2, idx3, sign);
    }
#endif
}
