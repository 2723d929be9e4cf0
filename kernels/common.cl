/* Shared definitions. The host prepends the compile-time constants:
 *   W, H            frame size (px)
 *   NW              32-pixel words per row of a state plane (ceil(W / 32))
 *   FSTRIDE         row stride of the frame and of the horizontal-pass buffer (= W)
 *   PSTRIDE, PPAD   row stride and left padding (elements) of the prefiltered image P
 *   SSTRIDE, SPAD   row stride and left padding of the summed-area tables (H + 1 rows)
 *   SAT_SLOTS       summed-area tables kept (max delay + 1)
 *   NCH             channels (scale, delay), sorted by increasing speed
 *   CH_K, CH_D, CH_T, CH_RING, CH_BASE   per-channel scale, delay, integer threshold,
 *                   state ring length (2D + 1) and first plane slot
 *   RADIUS, WEIGHTS prefilter half-width and integer taps (sum 256)
 *   TEX_T           textured-pixel threshold 2 * floor(theta * 256)
 *   SHARP           1 to accept the sharp template
 *   STATS_OFFSET    byte offset of the int32 statistics in the result buffer
 *   NBINS           orientation bins; ORIENT_C, ORIENT_S boundary table (x 2^14)
 */
#define PLANE_WORDS (H * NW)
/* plane index of (channel slot, polarity 0 = positive / 1 = negative) */
#define PLANE(slot, pol) (((slot) * 2 + (pol)) * PLANE_WORDS)

#define STAT_U 0
#define STAT_V 1
#define STAT_TEXTURED 2
#define STAT_SATURATED 3
#define STAT_CHANGED 4
#define STAT_HIST (STAT_CHANGED + NCH)

inline int pos_mod(int a, int m) { int r = a % m; return r < 0 ? r + m : r; }

/* Pack 8 lane masks (all-ones = true) into the low 8 bits of a word. Vectors stay at
 * 8 x 32 bits (one AVX2 register): PoCL 3.0 miscompiles some 16 x 32-bit code on
 * machines without AVX-512. */
inline uint pack8(int8 mask) {
    const uint8 bit = (uint8)(1u, 2u, 4u, 8u, 16u, 32u, 64u, 128u);
    uint8 b = as_uint8(mask) & bit;
    uint4 a4 = b.lo | b.hi;
    uint2 a2 = a4.lo | a4.hi;
    return a2.x | a2.y;
}
