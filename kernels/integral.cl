/* Stage 2: row prefix sums turn the column sums into the summed-area table
 * S[y + 1][SPAD + x + 1] = sum of P over [0..y] x [0..x] (uint16, wrapping; row 0 and
 * column SPAD stay 0). One work item per row. */
__kernel void integral_rows(__global ushort *sat, int slot)
{
    const int y = get_global_id(0);
    if (y >= H) return;  /* the global size is padded to whole work-groups */
    __global ushort *row = sat + slot * SAT_SIZE + (y + 1) * SSTRIDE + SPAD + 1;
    ushort acc = 0;
    for (int x = 0; x < W; x++) {
        acc += row[x];
        row[x] = acc;
    }
}
