/* Stage 5: the summary's evidence, from the flow codes. One work item per row: counts
 * detections, and on every EVIDENCE_ROW_STEP-th row bins each detection by (axis, signed
 * channel, orientation of the gradient of the receptor image R_k at the middle receptor B
 * at t - D). */

/* |table| <= 2^14 and |g| < 2^16 (box sums of an 8-bit image, k <= 15), so the cross
 * products below fit in 32 bits */
__constant int OC[NBINS - 1] = { ORIENT_C };
__constant int OS[NBINS - 1] = { ORIENT_S };

inline int box_at(__global const ushort *S, int cx, int cy, int r)
{
    __global const ushort *top = S + (cy - r) * SSTRIDE + SPAD + cx - r;
    __global const ushort *bot = S + (cy + r + 1) * SSTRIDE + SPAD + cx - r;
    const int w = 2 * r + 1;
    return (ushort)(bot[w] - top[w] - bot[0] + top[0]);  /* exact below 2^16 */
}

/* 1 when the gradient lies at or beyond boundary b (the exact integer test) */
#define BEYOND(b) (OC[(b)] * gy - OS[(b)] * gx >= 0)

inline int orientation_bin(int gx, int gy)
{
    if (gy < 0 || (gy == 0 && gx < 0)) { gx = -gx; gy = -gy; }
    /* The bin is the number of boundaries b with OC[b] gy - OS[b] gx >= 0. Guess it from a
     * cheap arctangent (max error ~0.25 deg, bins are 2.8 deg wide), then let the exact
     * integer test move it: the result is the exact count, like the reference's. */
    const float ax = fabs((float)gx), ay = (float)gy;
    const float t = fmin(ax, ay) / fmax(fmax(ax, ay), 1.0f);
    float a = t * (0.7853982f + 0.273f * (1.0f - t));            /* atan(t), t in [0, 1] */
    if (ay > ax) a = 1.5707963f - a;
    if (gx < 0) a = 3.1415927f - a;
    int n = (int)(a * (NBINS / 3.1415927f));
    n = n < 0 ? 0 : (n > NBINS - 1 ? NBINS - 1 : n);
    /* the guess is off by at most one bin: one branch-free step each way */
    const int below = n > 0 ? n - 1 : 0, at = n < NBINS - 1 ? n : NBINS - 2;
    n -= (n > 0) & !BEYOND(below);
    n += (n < NBINS - 1) & BEYOND(at > n ? n : at);
    return n;
}

/* nonzero bytes of a 64-bit word */
inline int nonzero_bytes(ulong v)
{
    v |= v >> 4;
    v |= v >> 2;
    v |= v >> 1;
    return __builtin_popcountl(v & 0x0101010101010101ul);
}

__kernel void summary_evidence(__global char *result, __global const ushort *sat, int t)
{
    const int y = get_global_id(0);
    if (y >= H) return;  /* the global size is padded to whole work-groups */
    __global int *stats = (__global int *)(result + STATS_OFFSET);
    const int sampled = (y % EVIDENCE_ROW_STEP) == 0;
    /* HIST_COPIES histograms, one per work-group modulo the count: the two CPU threads
     * then rarely increment the same cache line (the host adds the copies up) */
    __global int *hist = stats + STAT_HIST + (get_group_id(0) % HIST_COPIES) * HIST_SIZE;
    for (int axis = 0; axis < 2; axis++) {
        __global const char *codes = result + axis * H * W + y * W;
        int count = 0;
        /* neighbouring detections along an edge often fall in the same bin: count runs
         * and flush each run with one atomic add */
        int run_bin = -1, run_len = 0, pos_bin = -1, pos_len = 0;
        for (int x0 = 0; x0 < W; x0 += 8) {
            ulong v = 0;
            if (x0 + 8 <= W) {
                v = ((__global const ulong_u *)(codes + x0))->v;
            } else {
                for (int l = 0; x0 + l < W; l++) v |= (ulong)(uchar)codes[x0 + l] << (8 * l);
            }
            if (v == 0) continue;
            count += nonzero_bytes(v);
            if (!sampled) continue;
            for (int l = 0; l < 8; l++) {
                const int code = (char)(v >> (8 * l));
                if (code == 0) continue;
                const int x = x0 + l;
                const int c = (code > 0 ? code : -code) - 1;
                const int negative = code < 0;
                const int where = axis ? y * POS_BINS / H : x * POS_BINS / W;
                const int pbin = ((axis * 2 * NCH) + 2 * c + negative) * POS_BINS + where;
                if (pbin != pos_bin) {
                    if (pos_len) ATOMIC_ADD(stats + STAT_POS + pos_bin, pos_len);
                    pos_bin = pbin;
                    pos_len = 0;
                }
                pos_len++;
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
                const int bin = (axis * 2 * NCH + 2 * c + negative) * NBINS + orientation_bin(gx, gy);
                if (bin != run_bin) {
                    if (run_len) ATOMIC_ADD(hist + run_bin, run_len);
                    run_bin = bin;
                    run_len = 0;
                }
                run_len++;
            }
        }
        if (run_len) ATOMIC_ADD(hist + run_bin, run_len);
        if (pos_len) ATOMIC_ADD(stats + STAT_POS + pos_bin, pos_len);
        if (count) ATOMIC_ADD(stats + (axis ? STAT_V : STAT_U), count);
    }
}
