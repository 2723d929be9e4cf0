/* Stage 4: Elementary Velocity Detectors (paper section 3) and fusion, bit-sliced.
 * One work item per 8 consecutive 32-pixel words of a row (256 pixels, one uint8 vector
 * per bit plane); every template test is a few bitwise operations on whole vectors. The
 * state planes carry zero padding (a word left and right, PADR rows above and below), so
 * nothing tests bounds.
 *
 * For channel (k, D), direction delta and pixel A = x: B = x + k delta, C = x + 2k delta;
 * the velocity template fires when the same (polarity, type) motion template matches
 * A->B on the states at (t-2D, t-D) and B->C on the states at (t-D, t).
 * Fusion: the fastest channel that fires wins; both directions at that channel =
 * ambiguous (no output). Output: int8 codes +-(c+1) per pixel and axis. */

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

/* byte j of the result is bit j of the low 4 bits of m (one byte per pixel) */
inline uint8 spread4(uint8 m)
{
    return ((m & 0xFu) * 0x00204081u) & 0x01010101u;
}

__kernel void velocity_detectors(__global const uint *planes, __global char *result,
                                 __global uint *debug, int t)
{
    const int i = get_global_id(0) * 8;   /* first word */
    const int y = get_global_id(1);
    if (y >= H) return;  /* the global size is padded to whole work-groups */
    uint8 decided[2], sign[2], idx[2][4];
    for (int a = 0; a < 2; a++) {
        decided[a] = sign[a] = (uint8)(0u);
        for (int b = 0; b < 4; b++) idx[a][b] = (uint8)(0u);
    }

#pragma unroll
    for (int c = NCH - 1; c >= 0; c--) {
        const int k = CK[c], D = CD[c], L = CRING[c], base = CBASE[c];
        const int s0 = base + pos_mod(t - 2 * D, L), s1 = base + pos_mod(t - D, L), s2 = base + t % L;
        __global const uint *P0 = planes + PLANE_ROW(s0, 0, y) + i, *N0 = planes + PLANE_ROW(s0, 1, y) + i;
        __global const uint *P1 = planes + PLANE_ROW(s1, 0, y) + i, *N1 = planes + PLANE_ROW(s1, 1, y) + i;
        __global const uint *P2 = planes + PLANE_ROW(s2, 0, y) + i, *N2 = planes + PLANE_ROW(s2, 1, y) + i;
        const uint8 pa0 = LOAD_W8(P0), na0 = LOAD_W8(N0), pa1 = LOAD_W8(P1), na1 = LOAD_W8(N1);
        const uint8 za1 = ~(pa1 | na1);
        uint8 m[4];
#pragma unroll
        for (int dir = 0; dir < 4; dir++) {
            /* E, W: neighbours along the row; S, N: neighbours k rows away */
            const int dx = dir == 0 ? k : (dir == 1 ? -k : 0);
            const int dy = dir == 2 ? k : (dir == 3 ? -k : 0);
            const uint8 pb0 = at(P0, dy, dx), nb0 = at(N0, dy, dx);
            const uint8 pb1 = at(P1, dy, dx), nb1 = at(N1, dy, dx);
            const uint8 pb2 = at(P2, dy, dx), nb2 = at(N2, dy, dx);
            const uint8 pc1 = at(P1, 2 * dy, 2 * dx), nc1 = at(N1, 2 * dy, 2 * dx);
            const uint8 pc2 = at(P2, 2 * dy, 2 * dx), nc2 = at(N2, 2 * dy, 2 * dx);
            const uint8 zb0 = ~(pb0 | nb0), zb2 = ~(pb2 | nb2), zc1 = ~(pc1 | nc1);
            /* start [p 0 / p p] on both links */
            const uint8 sp = pa0 & zb0 & pa1 & pb1 & zc1 & pb2 & pc2;
            const uint8 sn = na0 & zb0 & na1 & nb1 & zc1 & nb2 & nc2;
            /* end [p p / 0 p] on both links */
            const uint8 ep = pa0 & pb0 & za1 & pb1 & pc1 & zb2 & pc2;
            const uint8 en = na0 & nb0 & za1 & nb1 & nc1 & zb2 & nc2;
            uint8 fired = sp | sn | ep | en;
#if SHARP
            /* sharp [p 0 / 0 p] on both links */
            fired |= (pa0 & zb0 & za1 & pb1 & zc1 & zb2 & pc2) | (na0 & zb0 & za1 & nb1 & zc1 & zb2 & nc2);
#endif
            m[dir] = fired;
        }
#ifdef DEBUG_MATCHES
        for (int dir = 0; dir < 4; dir++)
            if (i < NW) STORE_W8(debug + ((c * 4 + dir) * H + y) * NWP + i, m[dir]);
#endif
#pragma unroll
        for (int axis = 0; axis < 2; axis++) {
            const uint8 mp = m[2 * axis], mn = m[2 * axis + 1];
            const uint8 p = mp & ~decided[axis], n = mn & ~decided[axis];
            sign[axis] |= n & ~p;
#pragma unroll
            for (int b = 0; b < 4; b++)
                if (((c + 1) >> b) & 1) idx[axis][b] |= p ^ n;
            decided[axis] |= mp | mn;
        }
    }

    /* Codes, 4 pixels per 32-bit lane: one byte per pixel built from the index planes;
     * negative codes negated bytewise (no carries: codes are 1..15). */
#pragma unroll
    for (int axis = 0; axis < 2; axis++) {
        __global char *out = result + axis * H * W + y * W;
#pragma unroll
        for (int q = 0; q < 8; q++) {
            const uint sh = 4 * q;
            uint8 code = spread4(idx[axis][0] >> sh) | (spread4(idx[axis][1] >> sh) << 1u)
                       | (spread4(idx[axis][2] >> sh) << 2u) | (spread4(idx[axis][3] >> sh) << 3u);
            const uint8 sg = spread4(sign[axis] >> sh);
            code = (code ^ (sg * 0xFFu)) + sg;
            const uint lanes[8] = {code.s0, code.s1, code.s2, code.s3, code.s4, code.s5, code.s6, code.s7};
            for (int w = 0; w < 8; w++) {
                const int x = (i + w) * 32 + 4 * q;
                if (x + 4 <= W) {
                    STORE_U32(out + x, lanes[w]);
                } else {
                    for (int l = 0; x + l < W; l++) out[x + l] = (char)(lanes[w] >> (8 * l));
                }
            }
        }
    }
}
