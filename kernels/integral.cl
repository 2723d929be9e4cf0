/* Stage 2: row prefix sums turn the column sums into the summed-area table
 * S[y + 1][SPAD + x + 1] = sum of P over [0..y] x [0..x] (uint16, wrapping; row 0 and
 * column SPAD stay 0). One work item per row, 16 columns per step: an in-register
 * log-step prefix (lane shifts within each 8-lane half, which AVX2 does in one vpslldq,
 * then the low half's total into the high half) plus the running total of the row.
 * With DSAT, each finished row is also subtracted from the same row of the previous
 * frame's table (slot - 1, finished a frame ago): dsat = S_t - S_(t-1), the summed-area
 * table of P_t - P_(t-1) (uint16, wrapping), from which ternary_states takes the delay-1
 * differences of the scales k > 1 in 4 loads instead of 8 (at k = 13, 15 where the wrapped
 * value is exact, see wrapped_difference32). At t = 0 (and after reset())
 * the previous slot is stale or zero: nothing reads dsat before t = 1.
 * With COMPENSATE, work item 0 adds up the prefilter's strip sums into the frame's pixel
 * sum of P, kept per slot of P (bright[0 .. P_SLOTS - 1]), and from those the exposure
 * gain of each channel over its delay (bright[BRIGHT_RATIO + c]), once per frame for all
 * the rows of ternary_states. */
#define EMD_Z (ushort16)(0)
/* Lane shifts (index 16: a zero lane): clang's constant shuffle on PoCL, which becomes one
 * vpslldq (PoCL scalarises OpenCL's shuffle2); the standard shuffle2 elsewhere (OpenCL C
 * has no variadic macros: each shift is spelled out twice). */
#ifdef EMD_CLANG_BUILTINS
#define SHL1(v) __builtin_shufflevector(v, EMD_Z, 16, 0, 1, 2, 3, 4, 5, 6, 16, 8, 9, 10, 11, 12, 13, 14)
#define SHL2(v) __builtin_shufflevector(v, EMD_Z, 16, 16, 0, 1, 2, 3, 4, 5, 16, 16, 8, 9, 10, 11, 12, 13)
#define SHL4(v) __builtin_shufflevector(v, EMD_Z, 16, 16, 16, 16, 0, 1, 2, 3, 16, 16, 16, 16, 8, 9, 10, 11)
#define LOW7(v) __builtin_shufflevector(v, EMD_Z, 16, 16, 16, 16, 16, 16, 16, 16, 7, 7, 7, 7, 7, 7, 7, 7)
#define ALL15(v) __builtin_shufflevector(v, v, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15)
#else
#define SHL1(v) shuffle2(v, EMD_Z, (ushort16)(16, 0, 1, 2, 3, 4, 5, 6, 16, 8, 9, 10, 11, 12, 13, 14))
#define SHL2(v) shuffle2(v, EMD_Z, (ushort16)(16, 16, 0, 1, 2, 3, 4, 5, 16, 16, 8, 9, 10, 11, 12, 13))
#define SHL4(v) shuffle2(v, EMD_Z, (ushort16)(16, 16, 16, 16, 0, 1, 2, 3, 16, 16, 16, 16, 8, 9, 10, 11))
#define LOW7(v) shuffle2(v, EMD_Z, (ushort16)(16, 16, 16, 16, 16, 16, 16, 16, 7, 7, 7, 7, 7, 7, 7, 7))
#define ALL15(v) shuffle2(v, v, (ushort16)(15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 15))
#endif

__kernel void integral_rows(__global ushort *sat, __global ushort *dsat, int slot,
                            __global uint *bright, int p_slot)
{
    const int y = get_global_id(0);
    if (y >= H) return;  /* the global size is padded to whole work-groups */
#if COMPENSATE
    if (y == 0) {  /* the frame's pixel sum of P from the prefilter's strip sums */
        uint total = 0;
        for (int j = 0; j < NSTRIPS; j++) total += bright[P_SLOTS + p_slot * NSTRIPS + j];
        bright[p_slot] = total;
        /* the gain over D frames, x256, rounded, as EngineParams.brightness_ratio_q
         * (pixel sums < 2^32, their products in 64 bits); before D frames exist the
         * channel has no states, and its ratio is never read */
        for (int c = 0; c < NCH; c++) {
            const long then_sum = (long)bright[pos_mod(p_slot - CD[c], P_SLOTS)];
            long q = 256;
            if (then_sum > 0) q = (512 * (long)total + then_sum) / (2 * then_sum);
            bright[BRIGHT_RATIO + c] = (uint)(q < BRIGHTNESS_RATIO_MAX_Q ? q : BRIGHTNESS_RATIO_MAX_Q);
        }
    }
#endif
    __global ushort *row = sat + slot * SAT_SIZE + (y + 1) * SSTRIDE + SPAD + 1;
#if DSAT
    const int prev = slot == 0 ? SAT_SLOTS - 1 : slot - 1;
    __global const ushort *prow = sat + prev * SAT_SIZE + (y + 1) * SSTRIDE + SPAD + 1;
    __global ushort *drow = dsat + (y + 1) * SSTRIDE + SPAD + 1;
#endif
    ushort16 carry = EMD_Z;
    int x = 0;
    for (; x + 16 <= W; x += 16) {
        ushort16 v = LOAD_US16(row + x);
        v += SHL1(v);
        v += SHL2(v);
        v += SHL4(v);
        v += LOW7(v);
        const ushort16 s = v + carry;
        STORE_US16(row + x, s);
#if DSAT
        STORE_US16(drow + x, s - LOAD_US16(prow + x));
#endif
        carry += ALL15(v);  /* off the prefix's path: one add of loop-carried latency */
    }
    ushort acc = carry.s0;
    for (; x < W; x++) {
        acc += row[x];
        row[x] = acc;
#if DSAT
        drow[x] = acc - prow[x];
#endif
    }
}
