/* Stage 1: integer Gaussian prefilter (paper section 4) and the column sums of the
 * summed-area table. One work item walks down a strip of 16 columns: it computes the
 * horizontal pass of the row RADIUS below (reads clamped to the frame, rounded to gray
 * levels), the vertical pass of the current row from the strip's own horizontal results,
 * and the running column sums (uint16 arithmetic wraps; every box sum taken from the table
 * is below 2^16, so box sums stay exact). */

__constant ushort PF_W[2 * RADIUS + 1] = { WEIGHTS };

inline ushort16 horizontal16(__global const uchar *row, int x0)
{
    ushort16 acc = (ushort16)(128);
    if (x0 >= RADIUS && x0 + 15 + RADIUS <= W - 1) {
        for (int i = 0; i < 2 * RADIUS + 1; i++)
            acc += PF_W[i] * convert_ushort16(LOAD_UC16(row + x0 + i - RADIUS));
    } else {
        ushort16_u tmp;
        ushort *lanes = (ushort *)&tmp;
        for (int l = 0; l < 16; l++) {
            uint s = 128;
            for (int i = 0; i < 2 * RADIUS + 1; i++)
                s += PF_W[i] * row[CLAMPI(x0 + l + i - RADIUS, 0, W - 1)];
            lanes[l] = (ushort)s;
        }
        acc = tmp.v;
    }
    return acc >> 8;
}

__kernel void prefilter_columns(__global const uchar *frame, __global uchar *hbuf,
                                __global uchar *P, __global ushort *sat, int slot)
{
    const int x0 = get_global_id(0) * 16;
    if (x0 >= W) return;  /* the global size is padded to whole work-groups */
    __global ushort *S = sat + slot * SAT_SIZE + SPAD + 1 + x0;
    for (int y = 0; y < RADIUS && y < H; y++)
        STORE_UC16(hbuf + y * HSTRIDE + x0, convert_uchar16(horizontal16(frame + y * W, x0)));
    ushort16 colsum = (ushort16)(0);
    for (int y = 0; y < H; y++) {
        if (y + RADIUS < H)
            STORE_UC16(hbuf + (y + RADIUS) * HSTRIDE + x0,
                       convert_uchar16(horizontal16(frame + (y + RADIUS) * W, x0)));
        ushort16 acc = (ushort16)(128);
        for (int j = 0; j < 2 * RADIUS + 1; j++) {
            const int yy = CLAMPI(y + j - RADIUS, 0, H - 1);
            acc += PF_W[j] * convert_ushort16(LOAD_UC16(hbuf + yy * HSTRIDE + x0));
        }
        const ushort16 p = acc >> 8;
        /* lanes beyond W fall in padding that nothing reads unmasked */
        STORE_UC16(P + y * PSTRIDE + PPAD + x0, convert_uchar16(p));
        colsum += p;
        STORE_US16(S + (y + 1) * SSTRIDE, colsum);
    }
}
