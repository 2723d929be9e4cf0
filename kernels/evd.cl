/* Stage 4: Elementary Velocity Detectors (paper section 3), fusion and summary evidence.
 * One work item per row; 32 pixels per word, bit-sliced: every template test is a few
 * bitwise operations on whole words.
 *
 * For channel (k, D), direction delta and pixel A = x: B = x + k delta, C = x + 2k delta;
 * the velocity template fires when the same (polarity, type) motion template matches
 * A->B on the states at (t-2D, t-D) and B->C on the states at (t-D, t).
 * Fusion: the fastest channel that fires wins; both directions at that channel =
 * ambiguous (no output). Output: int8 codes +-(c+1) per pixel and axis. */

__constant int EK_[NCH] = { CH_K };
__constant int ED_[NCH] = { CH_D };
__constant int ERING_[NCH] = { CH_RING };
__constant int EBASE_[NCH] = { CH_BASE };
__constant long OC_[NBINS - 1] = { ORIENT_C };
__constant long OS_[NBINS - 1] = { ORIENT_S };
__constant ulong SPREAD_[256] = { SPREAD_TABLE };

/* Word of bits for pixels x0 + j + s (s may be negative), j = 0..31, from a row of words. */
inline uint shifted(__global const uint *row, int i, int s)
{
    const int q = s >> 5;             /* floor division by 32 */
    const int b = s & 31;
    const int i0 = i + q;
    uint lo = (i0 >= 0 && i0 < NW) ? row[i0] : 0u;
    if (b == 0) return lo;
    uint hi = (i0 + 1 >= 0 && i0 + 1 < NW) ? row[i0 + 1] : 0u;
    return (lo >> b) | (hi << (32 - b));
}

/* Words of the positive and negative planes at (row y, pixel offset s), 0 outside. */
inline uint2 fetch(__global const uint *planes, int slot, int y, int i, int s)
{
    if (y < 0 || y >= H) return (uint2)(0u);
    return (uint2)(shifted(planes + PLANE(slot, 0) + y * NW, i, s),
                   shifted(planes + PLANE(slot, 1) + y * NW, i, s));
}

/* Same (polarity, type) motion template on both links: a->b over (p0, p1) and b->c over
 * (p1, p2). Arguments are (pos, neg) words of the three receptors at three times. */
inline uint velocity_match(uint2 a0, uint2 a1, uint2 b0, uint2 b1, uint2 b2, uint2 c1, uint2 c2)
{
    uint fired = 0;
    const uint za1 = ~(a1.x | a1.y), zb0 = ~(b0.x | b0.y), zb1 = ~(b1.x | b1.y);
    const uint zb2 = ~(b2.x | b2.y), zc1 = ~(c1.x | c1.y);
    for (int pol = 0; pol < 2; pol++) {
        const uint A0 = pol ? a0.y : a0.x, A1 = pol ? a1.y : a1.x;
        const uint B0 = pol ? b0.y : b0.x, B1 = pol ? b1.y : b1.x, B2 = pol ? b2.y : b2.x;
        const uint C1 = pol ? c1.y : c1.x, C2 = pol ? c2.y : c2.x;
        /* start [p 0 / p p] */
        fired |= (A0 & zb0 & A1 & B1) & (B1 & zc1 & B2 & C2);
        /* end [p p / 0 p] */
        fired |= (A0 & B0 & za1 & B1) & (B1 & C1 & zb2 & C2);
#if SHARP
        /* sharp [p 0 / 0 p] */
        fired |= (A0 & zb0 & za1 & B1) & (B1 & zc1 & zb2 & C2);
#endif
    }
    return fired;
}

inline int box_at(__global const uint *S, int cx, int cy, int r)
{
    __global const uint *top = S + (cy - r) * SSTRIDE + SPAD + cx - r;
    __global const uint *bot = S + (cy + r + 1) * SSTRIDE + SPAD + cx - r;
    const int w = 2 * r + 1;
    return (int)(bot[w] - top[w] - bot[0] + top[0]);
}

inline int orientation_bin(long gx, long gy)
{
    if (gy < 0 || (gy == 0 && gx < 0)) { gx = -gx; gy = -gy; }
    /* count of boundaries b with OC_[b] * gy - OS_[b] * gx >= 0 (monotone: binary search) */
    int lo = 0, hi = NBINS - 1;
    while (lo < hi) {
        int mid = (lo + hi) >> 1;
        if (OC_[mid] * gy - OS_[mid] * gx >= 0) lo = mid + 1; else hi = mid;
    }
    return lo;
}

__kernel void velocity_detectors(__global const uint *planes, __global const uint *sat,
                                 __global char *result, __global uint *debug, int t)
{
    const int y = get_global_id(0);
    __global int *stats = (__global int *)(result + STATS_OFFSET);
    __global char *u_out = result + y * W;
    __global char *v_out = result + H * W + y * W;
    int n_u = 0, n_v = 0;

    for (int i = 0; i < NW; i++) {
        uint decided[2] = {0u, 0u}, sign[2] = {0u, 0u}, idx[2][4] = {{0u}};
        for (int c = NCH - 1; c >= 0; c--) {
            const int k = EK_[c], D = ED_[c], L = ERING_[c], base = EBASE_[c];
            const int s2 = base + t % L, s1 = base + pos_mod(t - D, L), s0 = base + pos_mod(t - 2 * D, L);
            const uint2 a0 = fetch(planes, s0, y, i, 0), a1 = fetch(planes, s1, y, i, 0);
            uint m[4];
            /* E, W: neighbours along the row; S, N: neighbours k rows away */
            for (int dir = 0; dir < 4; dir++) {
                const int dx = dir == 0 ? 1 : (dir == 1 ? -1 : 0);
                const int dy = dir == 2 ? 1 : (dir == 3 ? -1 : 0);
                const uint2 b0 = fetch(planes, s0, y + k * dy, i, k * dx);
                const uint2 b1 = fetch(planes, s1, y + k * dy, i, k * dx);
                const uint2 b2 = fetch(planes, s2, y + k * dy, i, k * dx);
                const uint2 c1 = fetch(planes, s1, y + 2 * k * dy, i, 2 * k * dx);
                const uint2 c2 = fetch(planes, s2, y + 2 * k * dy, i, 2 * k * dx);
                m[dir] = velocity_match(a0, a1, b0, b1, b2, c1, c2);
            }
#ifdef DEBUG_MATCHES
            for (int dir = 0; dir < 4; dir++)
                debug[((c * 4 + dir) * H + y) * NW + i] = m[dir];
#endif
            for (int axis = 0; axis < 2; axis++) {
                const uint mp = m[2 * axis], mn = m[2 * axis + 1];
                const uint p = mp & ~decided[axis], n = mn & ~decided[axis];
                const uint win = (p & ~n) | (n & ~p);
                sign[axis] |= n & ~p;
                for (int b = 0; b < 4; b++)
                    if (((c + 1) >> b) & 1) idx[axis][b] |= win;
                decided[axis] |= mp | mn;
            }
        }
        /* unpack codes: two halves of 16 lanes */
        for (int axis = 0; axis < 2; axis++) {
            __global char *out = (axis ? v_out : u_out) + i * 32;
            const uint det = idx[axis][0] | idx[axis][1] | idx[axis][2] | idx[axis][3];
            if (axis) n_v += popcount(det); else n_u += popcount(det);
            /* 8 pixels at a time in a 64-bit word, one byte per pixel (SWAR): byte j of
             * SPREAD_[m] is bit j of m, so the code bytes are a sum of shifted spreads;
             * negative codes are negated bytewise (two's complement, no carries since
             * codes are 1..15). */
            for (int q = 0; q < 4; q++) {
                ulong code = 0;
                for (int b = 0; b < 4; b++)
                    code |= SPREAD_[(idx[axis][b] >> (8 * q)) & 0xFFu] << b;
                const ulong sg = SPREAD_[(sign[axis] >> (8 * q)) & 0xFFu];
                code = (code ^ (sg * 0xFFul)) + sg;
                const int x = i * 32 + 8 * q;
                if (x + 8 <= W) {
                    vstore8(as_char8(code), 0, out + 8 * q);
                } else {
                    for (int l = 0; x + l < W; l++) out[8 * q + l] = (char)(code >> (8 * l));
                }
            }
            /* summary evidence on even rows: gradient orientation at B at t - D */
            if ((y & 1) == 0 && det) {
                uint bits = det;
                while (bits) {
                    const int j = 31 - clz(bits & (0u - bits));
                    bits &= bits - 1;
                    int cidx = 0;
                    for (int b = 0; b < 4; b++) cidx |= ((idx[axis][b] >> j) & 1) << b;
                    const int c = cidx - 1;
                    const int negative = (sign[axis] >> j) & 1;
                    const int k = EK_[c], r = k / 2, D = ED_[c];
                    __global const uint *S = sat + pos_mod(t - D, SAT_SLOTS) * (H + 1) * SSTRIDE;
                    const int x = i * 32 + j;
                    const int step = negative ? -k : k;
                    const int bx = axis ? x : x + step;
                    const int by = axis ? y + step : y;
                    const long gx = box_at(S, min(bx + 1, W - 1 - r), by, r) - box_at(S, max(bx - 1, r), by, r);
                    const long gy = box_at(S, bx, min(by + 1, H - 1 - r), r) - box_at(S, bx, max(by - 1, r), r);
                    if (gx == 0 && gy == 0) continue;
                    const int bin = orientation_bin(gx, gy);
                    atomic_inc(stats + STAT_HIST + ((axis * 2 * NCH) + 2 * c + negative) * NBINS + bin);
                }
            }
        }
    }
    if (n_u) atomic_add(stats + STAT_U, n_u);
    if (n_v) atomic_add(stats + STAT_V, n_v);
}
