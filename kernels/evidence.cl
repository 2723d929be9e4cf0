/* The summary's evidence, binned by the detector kernel (evd.cl) on every
 * EVIDENCE_ROW_STEP-th row (and in the columns set in the EVIDENCE_COLUMNS word mask) right
 * after it has fused the row's detections: each detection
 * by (axis, signed channel, orientation of the gradient of the receptor image R_k at the
 * middle receptor B at t - D) and by position. */

__attribute__((always_inline)) inline int box_at(__global const ushort *S, int cx, int cy, int r)
{
    __global const ushort *top = S + (cy - r) * SSTRIDE + SPAD + cx - r;
    __global const ushort *bot = S + (cy + r + 1) * SSTRIDE + SPAD + cx - r;
    const int w = 2 * r + 1;
    return (ushort)(bot[w] - top[w] - bot[0] + top[0]);  /* exact below 2^16 */
}

/* The bin is the number of boundaries b with OC[b] gy - OS[b] gx >= 0 (gradient folded
 * into the upper half-plane). The boundaries are sorted by angle, so the test is true for
 * b < bin and false after. Two levels of eight independent tests in int8 vectors: the
 * boundaries 7, 15, ..., 55 give the bin's group of eight, the seven boundaries inside it
 * the rest. A binary search was a chain of six dependent load-multiply-compare steps. */
#if NBINS != 64
#error "the orientation search is written for 64 bins"
#endif
/* the boundary tables padded to 64 entries (the last lane of every group is masked),
 * aligned so a group of eight is one vector load (vload8 is a library call on PoCL);
 * |table| <= 2^14 and |g| < 2^16 (box sums of an 8-bit image, k <= 15), so the cross
 * products fit in 32 bits */
__constant int OC[NBINS] __attribute__((aligned(32))) = { ORIENT_C };
__constant int OS[NBINS] __attribute__((aligned(32))) = { ORIENT_S };

inline int count_beyond(int8 c, int8 s, int gx, int gy)
{
    /* lanes 0..6: -1 where the gradient lies at or beyond that boundary; lane 7 unused */
    const int8 beyond = (c * gy - s * gx >= 0) & (int8)(-1, -1, -1, -1, -1, -1, -1, 0);
    const int4 h = beyond.lo + beyond.hi;
    const int2 q = h.lo + h.hi;
    return -(q.x + q.y);
}

__attribute__((always_inline)) inline int orientation_bin(int gx, int gy)
{
    const int flip = -((gy < 0) | ((gy == 0) & (gx < 0)));
    gx = (gx ^ flip) - flip;
    gy = (gy ^ flip) - flip;
    const int8 c1 = (int8)(OC[7], OC[15], OC[23], OC[31], OC[39], OC[47], OC[55], 0);
    const int8 s1 = (int8)(OS[7], OS[15], OS[23], OS[31], OS[39], OS[47], OS[55], 0);
    const int group = count_beyond(c1, s1, gx, gy);
    return 8 * group + count_beyond(*(__constant const int8 *)(OC + 8 * group),
                                      *(__constant const int8 *)(OS + 8 * group), gx, gy);
}

/* Run-length counting: neighbouring detections along an edge often fall in the same bin,
 * so each run of equal bins is flushed with one atomic add. */
typedef struct { int bin, len; } bin_run;

__attribute__((always_inline)) inline void run_add(__global int *counts, bin_run *run, int bin, int n)
{
    if (bin != run->bin) {
        if (run->len) ATOMIC_ADD(counts + run->bin, run->len);
        run->bin = bin;
        run->len = 0;
    }
    run->len += n;
}

__attribute__((always_inline)) inline void run_flush(__global int *counts, bin_run *run)
{
    if (run->len) ATOMIC_ADD(counts + run->bin, run->len);
    run->bin = -1;
    run->len = 0;
}

#if NCLASS > 1
__constant int CSTEP[NCLASS - 1] = { CLASS_STEPS };
#endif

/* Position bins of the detections m of word i of row y (bs: their signs), by popcount:
 * a vertical detection's bin is its row's, a horizontal one's its column's (a word spans
 * at most a few column bins). pos = first bin of the channel's positive code. */
__attribute__((always_inline)) inline void count_positions(__global int *positions, bin_run *run, int pos,
                                                           int axis, int y, int i, uint m, uint bs)
{
    while (m) {
        int where, lim = 32;
        if (axis) {
            where = y * POS_BINS / H;
        } else {
            where = (i * 32 + (int)CTZ(m)) * POS_BINS / W;
            /* lanes before the first column of the next bin, ceil((where + 1) W / POS_BINS) */
            lim = ((where + 1) * W + POS_BINS - 1) / POS_BINS - i * 32;
        }
        const uint seg = lim >= 32 ? m : m & ((1u << lim) - 1u);
        m &= ~seg;
        const int minus = (int)POPCOUNT(seg & bs), plus = (int)POPCOUNT(seg) - minus;
        if (plus) run_add(positions, run, pos + where, plus);
        if (minus) run_add(positions, run, pos + POS_BINS + where, minus);
    }
}

/* Bin the detections of word i of row y (theta_q: the threshold there; bit planes
 * b0..b3 = channel index c + 1, bs = sign) of one axis (0 horizontal, 1 vertical, 2 and 3
 * the diagonals B = A + k (1, 1) and A + k (1, -1), which have no position histogram)
 * into the position and orientation
 * histograms, channel by channel: a
 * channel's detections share its scale, delay and table, and their positions are counted
 * by popcount. The gradient of a scale-1 receptor image is the prefiltered image's own
 * (from the ring of P; the tables keep only the frames the larger scales need). */
inline void bin_detections(__global int *positions, __global int *hist, __global const ushort *sat,
                           __global const uchar *P, __global const uint *bright, int t, int theta_q,
                           int axis, int y, int i, uint b0, uint b1, uint b2, uint b3, uint bs,
                           bin_run *pos_run, bin_run *hist_run)
{
    const uint any = (b0 | b1 | b2 | b3) & EVIDENCE_COLUMNS;
    if (!any) return;
#pragma unroll
    for (int c = 0; c < NCH; c++) {
        const int v = c + 1;
        uint m = any & ((v & 1) ? b0 : ~b0) & ((v & 2) ? b1 : ~b1) & ((v & 4) ? b2 : ~b2)
                     & ((v & 8) ? b3 : ~b3);
        if (!m) continue;
        if (axis < 2) count_positions(positions, pos_run, (axis * 2 * NCH + 2 * c) * POS_BINS, axis, y, i, m, bs);
        const int k = CK[c], r = k / 2, D = CD[c];
        __global const uchar *R = P + pos_mod(t - D, P_SLOTS) * P_SIZE + PPAD;
        __global const ushort *S = sat + pos_mod(t - D, SAT_SLOTS) * SAT_SIZE;
#if NCLASS > 1
        const int unit = 2 * theta_q * k * k;
        /* the gradient is of t - D, the threshold of t: the channel's exposure gain over D
         * (x256, integral.cl) brings the gradient to the brightness of t */
        const int gain_q = COMPENSATE ? (int)bright[BRIGHT_RATIO + c] : 256;
#endif
        const int row = (axis * 2 * NCH + 2 * c) * NCLASS * NBINS;
        while (m) {
            const uint l = (uint)CTZ(m);
            m &= m - 1;
            const int x = i * 32 + (int)l;
            const int negative = (int)((bs >> l) & 1u);
            const int step = negative ? -k : k;
            /* B = A + step (ex, ey) */
            const int bx = axis == 1 ? x : x + step;
            const int by = axis == 0 ? y : (axis == 3 ? y - step : y + step);
            const int xr = bx + 1 < W - 1 - r ? bx + 1 : W - 1 - r;
            const int xl = bx - 1 > r ? bx - 1 : r;
            const int yd = by + 1 < H - 1 - r ? by + 1 : H - 1 - r;
            const int yu = by - 1 > r ? by - 1 : r;
            int gx, gy;
            if (k == 1) {
                /* a 1x1 box is the pixel: the same values the table would give */
                gx = (int)R[by * PSTRIDE + xr] - (int)R[by * PSTRIDE + xl];
                gy = (int)R[yd * PSTRIDE + bx] - (int)R[yu * PSTRIDE + bx];
            } else {
                gx = box_at(S, xr, by, r) - box_at(S, xl, by, r);
                gy = box_at(S, bx, yd, r) - box_at(S, bx, yu, r);
            }
            if (gx == 0 && gy == 0) continue;
            int cls = 0;
#if NCLASS > 1
            /* gradient-strength class (|g|_1 < 2^17 and gain_q <= 2^12, 8 theta_q k^2 < 2^23:
             * no overflow) */
            const int strength = 2 * gain_q * ((gx < 0 ? -gx : gx) + (gy < 0 ? -gy : gy));
            for (int s = 0; s < NCLASS - 1; s++) cls += strength >= CSTEP[s] * unit;
#endif
            run_add(hist, hist_run, row + (negative * NCLASS + cls) * NBINS + orientation_bin(gx, gy), 1);
        }
    }
}
