/* Stage 1: integer Gaussian prefilter (paper section 4), separable, reads clamped to the
 * frame. 16 pixels per work item. Output P in 1/256 gray levels: (sum + 128) >> 8. */

__constant int PF_W[2 * RADIUS + 1] = { WEIGHTS };

/* Horizontal pass: frame (uchar, stride FSTRIDE) -> hbuf (ushort, stride FSTRIDE).
 * Also counts saturated pixels (<= 2 or >= 253) on even rows. */
__kernel void prefilter_rows(__global const uchar *frame, __global ushort *hbuf,
                             __global char *result)
{
    const int x0 = get_global_id(0) * 16;
    const int y = get_global_id(1);
    __global const uchar *row = frame + y * FSTRIDE;
    ushort16 acc;
    if (x0 >= RADIUS && x0 + 15 + RADIUS <= W - 1) {
        acc = (ushort16)(0);
        for (int i = 0; i < 2 * RADIUS + 1; i++)
            acc += (ushort)PF_W[i] * convert_ushort16(vload16(0, row + x0 + i - RADIUS));
    } else {
        ushort tmp[16];
        for (int l = 0; l < 16; l++) {
            int s = 0;
            for (int i = 0; i < 2 * RADIUS + 1; i++)
                s += PF_W[i] * row[clamp(x0 + l + i - RADIUS, 0, W - 1)];
            tmp[l] = (ushort)s;
        }
        acc = vload16(0, tmp);
    }
    if (x0 + 15 < W) {
        vstore16(acc, 0, hbuf + y * FSTRIDE + x0);
    } else {
        ushort tmp[16];
        vstore16(acc, 0, tmp);
        for (int l = 0; x0 + l < W; l++) hbuf[y * FSTRIDE + x0 + l] = tmp[l];
    }
    if ((y & 1) == 0) {
        int n = 0;
        for (int l = 0; l < 16 && x0 + l < W; l++) {
            uchar p = row[x0 + l];
            n += (p <= 2 || p >= 253);
        }
        if (n) atomic_add((__global int *)(result + STATS_OFFSET) + STAT_SATURATED, n);
    }
}

/* Vertical pass: hbuf -> P (ushort, stride PSTRIDE, PPAD left padding). */
__kernel void prefilter_cols(__global const ushort *hbuf, __global ushort *P)
{
    const int x0 = get_global_id(0) * 16;
    const int y = get_global_id(1);
    /* two 8-lane accumulators: a loop-carried 512-bit vector breaks PoCL 3.0's code
     * generation on AVX2 machines (broken kernel cache entries / LLVM aborts) */
    uint8 lo = (uint8)(128), hi = (uint8)(128);
    for (int j = 0; j < 2 * RADIUS + 1; j++) {
        __global const ushort *src = hbuf + clamp(y + j - RADIUS, 0, H - 1) * FSTRIDE + x0;
        lo += (uint)PF_W[j] * convert_uint8(vload8(0, src));
        hi += (uint)PF_W[j] * convert_uint8(vload8(1, src));
    }
    ushort16 out = (ushort16)(convert_ushort8(lo >> 8), convert_ushort8(hi >> 8));
    /* lanes beyond W land in the row's right padding, which nothing reads unmasked */
    vstore16(out, 0, P + y * PSTRIDE + PPAD + x0);
}
