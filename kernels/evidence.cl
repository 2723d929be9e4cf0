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
 * into the upper half-plane), found without testing them all: the pseudo-angle
 * p = gy / (|gx| + gy) (2 - that for gx < 0) grows with the angle, and the cell
 * q = floor(ORIENT_CELLS gy / (|gx| + gy)) (2 ORIENT_CELLS - q for gx < 0) is within one
 * of ORIENT_CELLS p. ORIENT_CELL[cell] (orientation_cells() on the host, from exact
 * fractions) counts the boundaries certainly below the gradient; at most one more can be
 * (the host checks), the next in order, and that one is tested exactly. One division, one
 * table load and one test; the two rounds of eight boundary tests in int8 vectors before
 * this measured 0.05 ms slower per 640x480 frame of the extended model. */
__constant int OC[NBINS] = { ORIENT_C };
__constant int OS[NBINS] = { ORIENT_S };
__constant uchar ORIENT_CELL[2 * ORIENT_CELLS + 1] = { ORIENT_CELL_TABLE };

__attribute__((always_inline)) inline int orientation_bin(int gx, int gy)
{
    const int flip = -((gy < 0) | ((gy == 0) & (gx < 0)));
    gx = (gx ^ flip) - flip;
    gy = (gy ^ flip) - flip;
    const int ax = gx < 0 ? -gx : gx;
    /* gy < 2^16 (a difference of box sums below 2^16): the product stays below 2^26 */
    const int q = (int)(((uint)gy * ORIENT_CELLS) / (uint)(ax + gy));
    const int lo = ORIENT_CELL[gx < 0 ? 2 * ORIENT_CELLS - q : q];
    return lo + (lo < NBINS - 1 && OC[lo] * gy - OS[lo] * gx >= 0);
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

/* the 8 words of a run, as a vector or one by one (vector lanes cannot be indexed by a
 * variable; a union can, and vstore8 is a library call on PoCL) */
typedef union { uint8 v; uint w[8]; } run_words;

inline uint lane_or(uint8 v)
{
    const uint4 a = v.lo | v.hi;
    const uint2 b = a.lo | a.hi;
    return b.x | b.y;
}

/* Bin the detections of one axis (0 horizontal, 1 vertical, 2 and 3 the diagonals
 * B = A + k (1, 1) and A + k (1, -1), which have no position histogram) in the run of 8
 * words from flat word f (bit planes b0..b3 = channel index c + 1, bs = sign) that lie on
 * a sampled row, in the sampled columns, into the position and orientation histograms.
 * Channel by channel, each tested on the whole run at once (most channels have no
 * detection in most runs): a channel's detections share its scale, delay and table, and
 * their positions are counted by popcount. The gradient of a scale-1 receptor image is the
 * prefiltered image's own (from the ring of P; the tables keep only the frames the larger
 * scales need). */
inline void bin_evidence(__global int *positions, __global int *hist, __global const ushort *sat,
                         __global const uchar *P, __global const uint *bright, int t, int theta_q,
                         __global const int *theta_tiles, int axis, int f,
                         uint8 b0, uint8 b1, uint8 b2, uint8 b3, uint8 bs)
{
    run_words keep;
    for (int w = 0; w < 8; w++) {
        const int y = (f + w) / NWP, i = f + w - y * NWP - 1;
        keep.w[w] = y % EVIDENCE_ROW_STEP == 0 && y < H && i >= 0 ? EVIDENCE_COLUMNS : 0u;
    }
    const uint8 any = (b0 | b1 | b2 | b3) & keep.v;
    if (!lane_or(any)) return;
    const run_words sign = { bs };
    bin_run pos_run = { -1, 0 }, hist_run = { -1, 0 };
#pragma unroll
    for (int c = 0; c < NCH; c++) {
        const int v = c + 1;
        const run_words found = { any & ((v & 1) ? b0 : ~b0) & ((v & 2) ? b1 : ~b1) & ((v & 4) ? b2 : ~b2)
                                      & ((v & 8) ? b3 : ~b3) };
        if (!lane_or(found.v)) continue;
        const int k = CK[c], r = k / 2, D = CD[c];
        __global const uchar *R = P + pos_mod(t - D, P_SLOTS) * P_SIZE + PPAD;
        __global const ushort *S = sat + pos_mod(t - D, SAT_SLOTS) * SAT_SIZE;
#if NCLASS > 1
        /* the gradient is of t - D, the threshold of t: the channel's exposure gain over D
         * (x256, integral.cl) brings the gradient to the brightness of t */
        const int gain_q = COMPENSATE ? (int)bright[BRIGHT_RATIO + c] : 256;
#endif
        const int row = (axis * 2 * NCH + 2 * c) * NCLASS * NBINS;
        for (int w = 0; w < 8; w++) {
            uint m = found.w[w];
            if (!m) continue;
            const int y = (f + w) / NWP, i = f + w - y * NWP - 1;
            const uint bsw = sign.w[w];
            if (axis < 2) count_positions(positions, &pos_run, (axis * 2 * NCH + 2 * c) * POS_BINS, axis, y, i, m, bsw);
#if NCLASS > 1
            const int unit = 2 * THETA_AT(theta_q, theta_tiles, y, i) * k * k;
#endif
            while (m) {
                const uint l = (uint)CTZ(m);
                m &= m - 1;
                const int x = i * 32 + (int)l;
                const int negative = (int)((bsw >> l) & 1u);
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
                run_add(hist, &hist_run, row + (negative * NCLASS + cls) * NBINS + orientation_bin(gx, gy), 1);
            }
        }
    }
    if (axis < 2) run_flush(positions, &pos_run);
    run_flush(hist, &hist_run);
}
