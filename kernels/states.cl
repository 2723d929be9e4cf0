/* Stage 3: ternary states (paper section 2) of every channel, bit-packed.
 * One work item per row. For each 32-pixel word and channel (k, D):
 *   d = R_k(t) - R_k(t - D)    (box sums from the summed-area tables)
 *   state = +1 if d > T, -1 if d < -T, else 0, and 0 where the k x k block is not inside
 *   the frame; stored as two bit planes (positive, negative) in the channel's ring slot.
 * Also counts nonzero states per channel and textured pixels on even rows. */

__constant int K_[NCH] = { CH_K };
__constant int D_[NCH] = { CH_D };
__constant int T_[NCH] = { CH_T };
__constant int RING_[NCH] = { CH_RING };
__constant int BASE_[NCH] = { CH_BASE };

inline uint8 box8(__global const uint *S, int y, int x, int r)
{
    /* box sums over [y-r, y+r] x [x+lane-r, x+lane+r] for 8 lanes */
    __global const uint *top = S + (y - r) * SSTRIDE + SPAD + x - r;
    __global const uint *bot = S + (y + r + 1) * SSTRIDE + SPAD + x - r;
    const int w = 2 * r + 1;
    return vload8(0, bot + w) - vload8(0, top + w) - vload8(0, bot) + vload8(0, top);
}

__kernel void ternary_states(__global const uint *sat, __global uint *planes,
                             __global const ushort *P, __global char *result, int t)
{
    const int y = get_global_id(0);
    __global int *stats = (__global int *)(result + STATS_OFFSET);
    const int8 lane = (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    const int now_slot = t % SAT_SLOTS;
    __global const uint *S_now = sat + now_slot * (H + 1) * SSTRIDE;

    for (int c = 0; c < NCH; c++) {
        const int k = K_[c], r = k / 2, D = D_[c], T = T_[c];
        const int slot = BASE_[c] + t % RING_[c];
        __global uint *pos_row = planes + PLANE(slot, 0) + y * NW;
        __global uint *neg_row = planes + PLANE(slot, 1) + y * NW;
        if (t < D || y < r || y > H - 1 - r) {
            for (int i = 0; i < NW; i++) { pos_row[i] = 0; neg_row[i] = 0; }
            continue;
        }
        __global const uint *S_then = sat + pos_mod(t - D, SAT_SLOTS) * (H + 1) * SSTRIDE;
        int changed = 0;
        for (int i = 0; i < NW; i++) {
            uint pw = 0, nw = 0;
            for (int part = 0; part < 4; part++) {
                const int x = i * 32 + part * 8;
                int8 d = as_int8(box8(S_now, y, x, r) - box8(S_then, y, x, r));
                int8 xs = lane + x;
                int8 valid = (xs >= r) & (xs <= W - 1 - r);
                pw |= pack8((d > T) & valid) << (part * 8);
                nw |= pack8((d < -T) & valid) << (part * 8);
            }
            pos_row[i] = pw;
            neg_row[i] = nw;
            changed += popcount(pw | nw);
        }
        if (changed) atomic_add(stats + STAT_CHANGED + c, changed);
    }

    /* textured pixels: even interior rows, |dP/dx| + |dP/dy| (central) > TEX_T */
    if ((y & 1) == 0 && y >= 2 && y <= H - 2) {
        int n = 0;
        __global const ushort *row = P + y * PSTRIDE + PPAD;
        for (int x = 0; x < W; x += 8) {
            int8 gx = convert_int8(vload8(0, row + x + 1)) - convert_int8(vload8(0, row + x - 1));
            int8 gy = convert_int8(vload8(0, row + PSTRIDE + x)) - convert_int8(vload8(0, row - PSTRIDE + x));
            int8 xs = lane + x;
            /* |g| as max(g, -g): PoCL 3.0 cannot scalarise abs() here */
            int8 hit = (max(gx, -gx) + max(gy, -gy) > TEX_T) & (xs >= 1) & (xs <= W - 2);
            n += popcount(pack8(hit));
        }
        if (n) atomic_add(stats + STAT_TEXTURED, n);
    }
}
