/* Stage 3: ternary states (paper section 2) of every channel, bit-packed.
 * One work item per row, 16 pixels per vector. For each 32-pixel word and channel (k, D):
 *   now = R_k(t), then = R_k(t - D)   (k x k box sums from the summed-area tables)
 *   state = +1 if now - then > T, -1 if then - now > T, else 0 (unsigned compares, so
 *   the 16-bit box sums never overflow), and 0 where the block is not inside the frame;
 *   for D = 1 and 1 < k <= 11, now - then is one box sum of the difference table dsat
 *   (= S_t - S_(t-1), see integral_rows): |now - then| <= 121 * 255 < 2^15, so the
 *   wrapped box sum read as int16 is exact (4 loads from one table instead of 8 from two);
 *   for D = 1 and k = 13, 15 the same box sum is exact in every word whose lanes stay
 *   within 65535 - 255 k^2 (wrapped_difference32), and the rare other words read both;
 *   for k = 1 the receptor is the prefiltered pixel itself: P_t - P_(t-D) from the ring
 *   of prefiltered frames (the slow channels of the extended model), compared byte-wise
 *   with saturating subtractions, 32 pixels at a time (exceeds32 in common.cl);
 * stored as two bit planes (positive, negative) in the channel's ring slot. With
 * COMPENSATE (brightness compensation) and an exposure gain rho = rq / 256 between the
 * two frames (rq = round(256 B_t / B_(t-D)) of the frames' pixel sums, see
 * EngineParams.brightness_ratio_q), a channel compares 256 now - rq then with
 * +-(256 T + 128) instead (box sums from the tables for every k > 1: the difference table
 * holds now - then only): for a gain within +-50 % in 16-bit lanes (gain16_short, and
 * gain16_wide for k = 13, 15), otherwise in 32-bit lanes; rq = 256 takes the paths above
 * unchanged. A moving camera changes the frame's brightness too (content enters and
 * leaves the view: over the camera photograph at 2-3 px/frame every frame has rq != 256),
 * so the compensated path is a common one, not only an exposure drift's.
 * Also counts nonzero states per channel, textured pixels and saturated pixels. */

inline ushort16 box16(__global const ushort *S, int y, int x, int r)
{
    /* box sums over [y-r, y+r] x [x+lane-r, x+lane+r] for 16 lanes */
    __global const ushort *top = S + (y - r) * SSTRIDE + SPAD + x - r;
    __global const ushort *bot = S + (y + r + 1) * SSTRIDE + SPAD + x - r;
    const int w = 2 * r + 1;
    return LOAD_US16(bot + w) - LOAD_US16(top + w) - LOAD_US16(bot) + LOAD_US16(top);
}

/* bits of 256 now - rq then > T256 (p) and < -T256 (n) for 16 lanes (box sums below
 * 2^16 and rq <= BRIGHTNESS_RATIO_MAX_Q = 4096: every product fits in 32 bits) */
inline void gain16(int8 now_lo, int8 now_hi, int8 then_lo, int8 then_hi, int rq, int T256,
                   uint *p, uint *n)
{
    const int8 g_lo = (now_lo << 8) - rq * then_lo, g_hi = (now_hi << 8) - rq * then_hi;
    *p = pack16((short16)(convert_short8(g_lo > T256), convert_short8(g_hi > T256)));
    *n = pack16((short16)(convert_short8(g_lo < -T256), convert_short8(g_hi < -T256)));
}

/* The same test in 16-bit lanes, 16 pixels, for |delta| < 128, delta = rq - 256: with
 * d = now - then, 256 now - rq then = 256 d - delta then, and with then = 256 h + l
 * (l <= 255), delta then = 256 delta h + delta l. d and T are whole numbers, so
 * 256 d - delta then > 256 T + 128 <=> d > tp = T + delta h + floor((delta l + 128) / 256),
 * and < -(256 T + 128) <=> -d > tn = T - delta h + floor((128 - delta l) / 256): the same
 * bits as gain16, exactly. |delta l| <= 32385; box sums below 2^15 (k <= 11: h <= 120,
 * |delta h| <= 15240) with T <= 16000, or below 2^16 (k = 13, 15: h <= 224,
 * |delta h| <= 28448) with T <= 4000 (checked by the caller): tp and tn fit 16 bits. */
inline void shifted_thresholds(ushort16 then, short delta, short T, short16 *tp, short16 *tn)
{
    const short16 h = as_short16(then >> (ushort)8), l = as_short16(then & (ushort)255);
    const short16 dh = h * delta, dl = l * delta;
    *tp = T + dh + ((dl + (short)128) >> (short)8);
    *tn = T - dh + (((short)128 - dl) >> (short)8);
}

/* k <= 11: d = now - then is exact in 16 bits */
inline void gain16_short(short16 d, ushort16 then, short delta, short T, short16 *p, short16 *n)
{
    short16 tp, tn;
    shifted_thresholds(then, delta, T, &tp, &tn);
    *p = d > tp;
    *n = -d > tn;
}

/* now > then + t for 16 lanes of box sums below 2^16 and |t| < 2^15, without the 17 bits
 * now - then may need (k = 13, 15): sat(now - t) > then where t >= 0 (if now < t, both
 * sides are false), sat(now + |t|) > then where t < 0 (a saturated sum, 65535, exceeds
 * then as the exact one does) */
inline short16 above_shifted(ushort16 now, ushort16 then, short16 t)
{
    const short16 neg = t >> (short)15;
    const ushort16 mag = as_ushort16((t ^ neg) - neg), m = as_ushort16(neg);
    const ushort16 lhs = (subs_u16(now, mag) & ~m) | (adds_u16(now, mag) & m);
    return as_short16(lhs > then);
}

/* k = 13, 15: now - then may need 17 bits, so the tests go through above_shifted */
inline void gain16_wide(ushort16 now, ushort16 then, short delta, short T, short16 *p, short16 *n)
{
    short16 tp, tn;
    shifted_thresholds(then, delta, T, &tp, &tn);
    *p = above_shifted(now, then, tp);
    *n = above_shifted(then, now, tn);
}

/* gain16_short for 32 pixels (d0, then0: the first 16) */
inline void gain32_short(short16 d0, ushort16 then0, short16 d1, ushort16 then1, int rq, int T,
                         uint *pw, uint *nw)
{
    short16 p0, n0, p1, n1;
    gain16_short(d0, then0, (short)(rq - 256), (short)T, &p0, &n0);
    gain16_short(d1, then1, (short)(rq - 256), (short)T, &p1, &n1);
    *pw = pack32(p0, p1);
    *nw = pack32(n0, n1);
}

/* gain16 for 32 pixels from two 16-lane halves */
inline void gain32(ushort16 now0, ushort16 then0, ushort16 now1, ushort16 then1, int rq, int T256,
                   uint *pw, uint *nw)
{
    uint p0, n0, p1, n1;
    gain16(convert_int8(now0.lo), convert_int8(now0.hi), convert_int8(then0.lo), convert_int8(then0.hi),
           rq, T256, &p0, &n0);
    gain16(convert_int8(now1.lo), convert_int8(now1.hi), convert_int8(then1.lo), convert_int8(then1.hi),
           rq, T256, &p1, &n1);
    *pw = p0 | (p1 << 16);
    *nw = n0 | (n1 << 16);
}

/* bits of now - then > T for two 16-lane halves of 16-bit box sums (T >= 0):
 * sat(sat(now - T) - then) != 0 */
inline uint above32_u16(ushort16 now0, ushort16 then0, ushort16 now1, ushort16 then1, int T)
{
    const short16 z = (short16)(0);
    const ushort16 Tv = (ushort16)((ushort)(T > 65535 ? 65535 : T));
    return ~pack32(as_short16(subs_u16(subs_u16(now0, Tv), then0)) == z,
                   as_short16(subs_u16(subs_u16(now1, Tv), then1)) == z);
}

/* k = 13, 15 with D = 1: now - then for 32 pixels from the difference table. Its box sum is
 * now - then wrapped to 16 bits; as |now - then| <= 255 k^2, a wrapped value d16 with
 * |d16| <= 65535 - 255 k^2 is the true one (d16 -+ 65536 would be out of range). False,
 * with nothing written, if a lane is beyond that (a change of more than 132 gray levels on
 * average over the box at k = 13, 36 at k = 15): the caller then reads both tables. */
inline bool wrapped_difference32(__global const ushort *dsat, int y, int x, int r, int T, uint *pw, uint *nw)
{
    const int k = 2 * r + 1;
    const short lim = (short)(65535 - 255 * k * k), Ts = (short)CLAMPI(T, 0, 32767);
    const short16 d0 = as_short16(box16(dsat, y, x, r)), d1 = as_short16(box16(dsat, y, x + 16, r));
    if (pack32((d0 > lim) | (d0 < (short)-lim), (d1 > lim) | (d1 < (short)-lim)))
        return false;
    *pw = pack32(d0 > Ts, d1 > Ts);
    *nw = pack32(d0 < (short)-Ts, d1 < (short)-Ts);
    return true;
}

__kernel void ternary_states(__global const ushort *sat, __global const ushort *dsat, __global uint *planes,
                             __global const uchar *P, __global const uchar *frame,
                             __global char *result, int t, int theta_q, __global const uint *bright,
                             __global const int *theta_tiles)
{
    const int y = get_global_id(0);
    if (y >= H) return;  /* the global size is padded to whole work-groups */
    /* this work-group's copy of the counters (common.cl) */
    __global int *stats = (__global int *)(result + STATS_OFFSET) + (get_group_id(0) % COUNTER_COPIES) * SLOT_INTS;
    __global const ushort *S_now = sat + (t % SAT_SLOTS) * SAT_SIZE;
    __global const uchar *P_now = P + (t % P_SLOTS) * P_SIZE;

    /* unrolled: k, r and the load offsets become constants */
    #pragma unroll
    for (int c = 0; c < NCH; c++) {
        const int k = CK[c], r = k / 2, D = CD[c];
        const int slot = CBASE[c] + t % CRING[c];
        __global uint *pos_row = planes + PLANE_ROW(slot, 0, y);
        __global uint *neg_row = planes + PLANE_ROW(slot, 1, y);
        if (t < D || y < r || y > H - 1 - r) {
            for (int i = 0; i < NW; i++) { pos_row[i] = 0; neg_row[i] = 0; }
            continue;
        }
        /* (S_then only for k > 1: the tables go back as far as those channels' delays) */
        __global const ushort *S_then = sat + pos_mod(t - D, SAT_SLOTS) * SAT_SIZE;
        __global const uchar *P_then = P + pos_mod(t - D, P_SLOTS) * P_SIZE;
        /* brightness compensation: the exposure gain over D frames, x256 (integral_rows) */
        const int rq = COMPENSATE ? (int)bright[BRIGHT_RATIO + c] : 256;
        /* words from i_edge on hold pixels past W - 1 - r; word 0 holds x < r */
        const int i_edge = (W - r) / 32;
        int changed = 0, step_changed = 0, brightening = 0;
        /* the gain's test fits 16-bit lanes (gain16_short; with the local threshold
         * theta_q is the largest tile's, so the test holds for every word: the row keeps
         * one path, and the paths give the same bits) */
        const bool short_gain = (rq > 128) & (rq < 384) & (((theta_q * k * k) >> 8) <= (k <= 11 ? 16000 : 4000));
        for (int i = 0; i < NW; i++) {
            const int x = i * 32;
            /* floor(theta k^2): the frame's threshold, or the word's tile's */
            const int T = (THETA_AT(theta_q, theta_tiles, y, i) * k * k) >> 8;
            /* the compensated change is not a whole number: > 256 T + 128 is the plain test
             * (> T, i.e. >= T + 1) on it rounded to whole units (EngineParams.compensated_threshold) */
            const int T256 = 256 * T + 128;
            /* the states without compensation (u..): the channel's own unless there is a
             * gain to compensate, and the exposure-step test's (finest channel) */
            uint pw, nw, upw = 0, unw = 0;
            /* a 1x1 receptor is the prefiltered pixel itself: P_t - P_(t-D) (k = 1 only) */
            __global const uchar *pn = P_now + y * PSTRIDE + PPAD + x, *pt = P_then + y * PSTRIDE + PPAD + x;
            if (rq == 256 || c == FINEST_CHANNEL) {
                if (k == 1) {  /* byte-wise */
                    const uchar Tb = (uchar)(T > 255 ? 255 : T);
                    upw = exceeds32(pn, pt, Tb);
                    unw = exceeds32(pt, pn, Tb);
                } else if (k <= 11) {
                    /* |now - then| <= 121 * 255 < 2^15: the int16 difference is exact */
                    const short Ts = (short)CLAMPI(T, 0, 32767);
                    short16 d0, d1;
                    if (D == 1) {
                        d0 = as_short16(box16(dsat, y, x, r));
                        d1 = as_short16(box16(dsat, y, x + 16, r));
                    } else {
                        d0 = as_short16(box16(S_now, y, x, r) - box16(S_then, y, x, r));
                        d1 = as_short16(box16(S_now, y, x + 16, r) - box16(S_then, y, x + 16, r));
                    }
                    upw = pack32(d0 > Ts, d1 > Ts);
                    unw = pack32(d0 < (short)-Ts, d1 < (short)-Ts);
                } else if (D == 1 && wrapped_difference32(dsat, y, x, r, T, &upw, &unw)) {
                    /* (4 loads a half instead of 8) */
                } else {
                    const ushort16 now0 = box16(S_now, y, x, r), then0 = box16(S_then, y, x, r);
                    const ushort16 now1 = box16(S_now, y, x + 16, r), then1 = box16(S_then, y, x + 16, r);
                    upw = above32_u16(now0, then0, now1, then1, T);
                    unw = above32_u16(then0, now0, then1, now1, T);
                }
            }
            if (rq == 256) {
                pw = upw;
                nw = unw;
            } else if (short_gain && k == 1) {
                const ushort16 then0 = convert_ushort16(LOAD_UC16(pt)), then1 = convert_ushort16(LOAD_UC16(pt + 16));
                gain32_short(as_short16(convert_ushort16(LOAD_UC16(pn)) - then0), then0,
                             as_short16(convert_ushort16(LOAD_UC16(pn + 16)) - then1), then1, rq, T, &pw, &nw);
            } else if (short_gain && k <= 11) {
                const ushort16 then0 = box16(S_then, y, x, r), then1 = box16(S_then, y, x + 16, r);
                gain32_short(as_short16(box16(S_now, y, x, r) - then0), then0,
                             as_short16(box16(S_now, y, x + 16, r) - then1), then1, rq, T, &pw, &nw);
            } else if (short_gain) {
                short16 p0, n0, p1, n1;
                gain16_wide(box16(S_now, y, x, r), box16(S_then, y, x, r), (short)(rq - 256), (short)T, &p0, &n0);
                gain16_wide(box16(S_now, y, x + 16, r), box16(S_then, y, x + 16, r), (short)(rq - 256), (short)T,
                            &p1, &n1);
                pw = pack32(p0, p1);
                nw = pack32(n0, n1);
            } else if (k == 1) {
                gain32(convert_ushort16(LOAD_UC16(pn)), convert_ushort16(LOAD_UC16(pt)),
                       convert_ushort16(LOAD_UC16(pn + 16)), convert_ushort16(LOAD_UC16(pt + 16)),
                       rq, T256, &pw, &nw);
            } else {
                gain32(box16(S_now, y, x, r), box16(S_then, y, x, r), box16(S_now, y, x + 16, r),
                       box16(S_then, y, x + 16, r), rq, T256, &pw, &nw);
            }
            if (i == 0 || i >= i_edge) {
                const uint valid = bit_range(r - x, W - 1 - r - x);
                pw &= valid;
                nw &= valid;
                upw &= valid;
                unw &= valid;
            }
            pos_row[i] = pw;
            neg_row[i] = nw;
            changed += POPCOUNT(pw | nw);
            if (c == FINEST_CHANNEL) {
                /* the exposure-step test's states: those without compensation */
                step_changed += POPCOUNT(upw | unw);
                brightening += POPCOUNT(upw);
            }
        }
        if (changed) ATOMIC_ADD(stats + STAT_CHANGED + c, changed);
        if (c == FINEST_CHANNEL && step_changed) ATOMIC_ADD(stats + STAT_STEP_CHANGED, step_changed);
        if (c == FINEST_CHANNEL && brightening) ATOMIC_ADD(stats + STAT_BRIGHTENING, brightening);
    }

    if ((y & 1) == 0) {
        /* textured: even interior rows, |dP/dx| + |dP/dy| (central differences) > floor(2
         * theta); contrast: the sum of that quantity (drives the adaptive threshold).
         * Counted per lane, summed once per row. */
        const short16 lane = (short16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
        int textured = 0, saturated = 0, contrast = 0;
#if LOCAL_THRESHOLD
        /* this row's contrast sum per tile (the host adds them up per tile) */
        __global int *tile_contrast = (__global int *)(result + STATS_OFFSET) + TILE_OFFSET + (y / 2) * NTX;
#define TILE_COLUMNS NTX
#else
#define TILE_COLUMNS 1
#endif
        if (y >= 2 && y <= H - 2) {
            __global const uchar *row = P_now + y * PSTRIDE + PPAD;
            short16 tex_n = (short16)(0);   /* lane counts: at most W / 16 */
            /* (one pass over the row without tiles; a tile's columns are whole 16-lane
             * vectors, TILE being a multiple of 32) */
            for (int tx = 0; tx < TILE_COLUMNS; tx++) {
#if LOCAL_THRESHOLD
                const int x_first = tx * TILE, x_end = x_first + TILE < W ? x_first + TILE : W;
#else
                const int x_first = 0, x_end = W;
#endif
                const short tex_t = (short)((2 * THETA_AT(theta_q, theta_tiles, y, x_first / 32)) >> 8);
                int8 con = (int8)(0);
                for (int x = x_first; x < x_end; x += 16) {
                    short16 gx = convert_short16(LOAD_UC16(row + x + 1)) - convert_short16(LOAD_UC16(row + x - 1));
                    short16 gy = convert_short16(LOAD_UC16(row + PSTRIDE + x)) - convert_short16(LOAD_UC16(row - PSTRIDE + x));
                    const short16 xs = lane + (short)x;
                    /* |g| by sign masks: PoCL 3.0 cannot scalarise abs() and calls max() */
                    const short16 sx = gx >> 15, sy = gy >> 15;
                    const short16 inside = (xs >= (short)1) & (xs <= (short)(W - 2));
                    const short16 g = (((gx ^ sx) - sx) + ((gy ^ sy) - sy)) & inside;
                    tex_n -= g > tex_t;
                    con += convert_int8(g.lo + g.hi);  /* <= 2 * 510: no overflow */
                }
                const int4 c4 = con.lo + con.hi;
                const int tile_sum = c4.x + c4.y + c4.z + c4.w;
#if LOCAL_THRESHOLD
                tile_contrast[tx] = tile_sum;
#endif
                contrast += tile_sum;
            }
            const short8 t8 = tex_n.lo + tex_n.hi;
            const int4 t4 = convert_int4(t8.lo) + convert_int4(t8.hi);
            textured = t4.x + t4.y + t4.z + t4.w;
        }
#if LOCAL_THRESHOLD
        else {
            for (int tx = 0; tx < NTX; tx++) tile_contrast[tx] = 0;
        }
#endif
#undef TILE_COLUMNS
        /* saturated: even rows, raw value <= 2 or >= 253, i.e. (uchar)(v + 3) <= 5 */
        __global const uchar *raw = frame + y * W;
        int x = 0;
        for (; x + 16 <= W; x += 16) {
            const uchar16 v = LOAD_UC16(raw + x) + (uchar)3;
            saturated += POPCOUNT(pack16(convert_short16(v <= (uchar)5)));
        }
        for (; x < W; x++) saturated += (raw[x] <= 2) | (raw[x] >= 253);
        if (textured) ATOMIC_ADD(stats + STAT_TEXTURED, textured);
        if (contrast) ATOMIC_ADD(stats + STAT_CONTRAST, contrast);
        if (saturated) ATOMIC_ADD(stats + STAT_SATURATED, saturated);
    }
}
