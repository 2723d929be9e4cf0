/* Stage 2: summed-area table of P, so every k x k receptor is 4 loads at any scale.
 * S has H + 1 rows; S[y + 1][SPAD + x + 1] = sum of P over [0..y] x [0..x]; row 0 and
 * column SPAD stay 0. uint32 arithmetic wraps, but every box sum taken from it is below
 * 2^32 (169 * 65280 < 2^24), so box sums are exact. */

/* Row prefix sums: one work item per row. */
__kernel void integral_rows(__global const ushort *P, __global uint *sat, int slot)
{
    __global uint *S = sat + slot * (H + 1) * SSTRIDE;
    const int y = get_global_id(0);
    __global const ushort *src = P + y * PSTRIDE + PPAD;
    __global uint *dst = S + (y + 1) * SSTRIDE + SPAD + 1;
    uint acc = 0;
    for (int x = 0; x < W; x++) {
        acc += src[x];
        dst[x] = acc;
    }
}

/* Column prefix sums: 8 columns per work item, down the rows. (A loop-carried uint16
 * accumulator makes PoCL 3.0's LLVM abort: "Do not know how to scalarize"; 8 lanes are
 * one AVX2 register anyway.) */
__kernel void integral_cols(__global uint *sat, int slot)
{
    __global uint *S = sat + slot * (H + 1) * SSTRIDE;
    const int x0 = SPAD + 1 + get_global_id(0) * 8;
    uint8 acc = (uint8)(0);
    for (int y = 1; y <= H; y++) {
        __global uint *p = S + y * SSTRIDE + x0;
        acc += vload8(0, p);
        vstore8(acc, 0, p);
    }
}
