/* Shared definitions. The host prepends the compile-time constants:
 *   W, H            frame size (px)
 *   NW              32-pixel words per row of a state plane (ceil(W / 32))
 *   NWP, PADR, PHEAD  plane row length (NW words and one zero word, so rows are separated
 *                   by a zero word), zero rows above and below each plane (2 * max scale)
 *                   and zero words before the first plane: the detectors never test bounds
 *   PSTRIDE, PPAD   row stride and left padding of the prefiltered image P (uchar)
 *   P_SIZE, P_SLOTS one slot of P (PSTRIDE * H) and the frames of P kept (max delay + 1)
 *   SSTRIDE, SPAD   row stride and left padding of the summed-area tables (ushort, H + 1 rows)
 *   SAT_SLOTS       summed-area tables kept (max delay of the scales > 1, plus 1)
 *   DSAT            1 if some channel has D = 1 and k > 1: integral_rows also writes the
 *                   difference table S_t - S_(t-1) that ternary_states reads for them
 *   NCH             channels (scale, delay), sorted by increasing speed
 *   COMPENSATE      1 for brightness compensation (EngineParams.brightness_compensation)
 *   BRIGHTNESS_RATIO_MAX_Q  largest exposure gain x256 it compensates (EngineParams)
 *   NSTRIPS         16-column strips of the prefilter (ceil(W / 16))
 *   CH_K, CH_D, CH_RING, CH_BASE   per-channel scale, delay, state ring length (2D + 1)
 *                   and first plane slot (the threshold theta_q = round(256 theta) is a
 *                   kernel argument: it adapts frame by frame in the adaptive mode)
 *   RADIUS, WEIGHTS prefilter half-width and integer taps (sum 256)
 *   SHARP           1 to accept the sharp template
 *   EVIDENCE        1 to compute the summary's evidence (histograms), 0 for the dense
 *                   field and the counters only (EngineParams.summary_evidence)
 *   EVIDENCE_ROW_STEP  rows between the rows whose detections feed the histogram
 *   EVIDENCE_COLUMNS   mask of the sampled columns within a 32-pixel word
 *   COUNTER_COPIES, SLOT_INTS, POS_COPIES, HIST_COPIES  copies of the counters (and their
 *                   spacing in ints) and of the position and orientation histograms: they
 *                   spread the atomic increments over cache lines (see STAT_POS below)
 *   POS_BINS        position bins of the detection position histogram
 *   FINEST_CHANNEL  channel whose positive states are counted (brightness steps)
 *   OUT_PLANE       words of one output bit plane: rows of NWP words like the state planes
 *                   (H NWP, rounded up to the detector kernel's 8-word runs)
 *   STATS_OFFSET    byte offset of the int32 statistics in the result buffer
 *   N_STATS         int32 statistics (counters, position and orientation histograms;
 *                   the counters only without EVIDENCE)
 *   NBINS           orientation bins; ORIENT_C, ORIENT_S boundary table (x 2^14)
 *   NCLASS, CLASS_STEPS  gradient-strength classes of the evidence and their steps m
 *                   (class = #{m : 512 |g|_1 >= m 2 theta_q k^2})
 *   LOCAL_THRESHOLD 1 for the local threshold (EngineParams.threshold_mode 'local'): the
 *                   threshold at a pixel is its tile's, theta_tiles[(y / TILE) NTX + x / TILE]
 *                   (a kernel argument written by the host per frame), instead of theta_q
 *   TILE, NTX       the tiles' side (a multiple of 32: a state word lies in one tile) and
 *                   tiles per row of tiles
 *   TILE_OFFSET     int offset (from STATS_OFFSET) of each even row's contrast sum per tile
 *                   ((y / 2) NTX + tile column; rows 0 and H - 1 store 0), which the host
 *                   adds up per tile for the next frame's thresholds
 *
 * Vectors are kept at 256 bits (ushort16, uint8): PoCL 3.0 miscompiles some 512-bit
 * vector code on machines without AVX-512 (LLVM aborts or broken cached binaries). */
#define PLANE_WORDS ((H + 2 * PADR) * NWP)
/* the fixed-point threshold of word i (32 px) of row y */
#if LOCAL_THRESHOLD
#define THETA_AT(theta_q, theta_tiles, y, i) ((theta_tiles)[((y) / TILE) * NTX + ((i) * 32) / TILE])
#else
#define THETA_AT(theta_q, theta_tiles, y, i) (theta_q)
#endif
/* first word of row y of the plane (ring slot, polarity 0 = positive / 1 = negative) */
#define PLANE_ROW(slot, pol, y) (PHEAD + (((slot) * 2 + (pol)) * PLANE_WORDS) + ((y) + PADR) * NWP + 1)
#define SAT_SIZE ((H + 1) * SSTRIDE)
/* brightness compensation's buffer: the pixel sum of each slot of P, the prefilter's
 * strip sums per slot, then each channel's exposure gain x256 (integral.cl) */
#define BRIGHT_RATIO (P_SLOTS * (1 + NSTRIPS))

#define STAT_U 0
#define STAT_V 1
#define STAT_TEXTURED 2
#define STAT_SATURATED 3
#define STAT_BRIGHTENING 4
#define STAT_CONTRAST 5
#define STAT_STEP_CHANGED 6
#define STAT_CHANGED 7
/* The statistics (int32 from STATS_OFFSET) start with COUNTER_COPIES copies of the
 * counters above, SLOT_INTS ints apart (whole cache lines): a work-group adds to copy
 * (group index modulo the count), so the CPU threads, which take neighbouring groups,
 * rarely increment the same cache line (atomics contended on one line took 0.03-0.04 ms
 * per 640x480 frame in each kernel); the host sums the copies. Then POS_COPIES position
 * histograms and HIST_COPIES orientation histograms, spread the same way. */
#define STAT_POS (COUNTER_COPIES * SLOT_INTS)
#define POS_SIZE (2 * 2 * NCH * POS_BINS)
#define STAT_HIST (STAT_POS + POS_COPIES * POS_SIZE)
/* detector axes binned: horizontal, vertical and, with DIAGONAL, the two diagonals */
#define EVIDENCE_AXES (DIAGONAL ? 4 : 2)
#define HIST_SIZE (EVIDENCE_AXES * 2 * NCH * NCLASS * NBINS)

__constant int CK[NCH] = { CH_K };
__constant int CD[NCH] = { CH_D };
__constant int CRING[NCH] = { CH_RING };
__constant int CBASE[NCH] = { CH_BASE };

/* Unaligned vector loads and stores. PoCL 3.0 does not inline vload16/vstore16 (a
 * library call per vector); a packed struct gives LLVM an align-1 load it turns into
 * one vmovdqu. */
typedef struct __attribute__((packed)) { uchar16 v; } uchar16_u;
typedef struct __attribute__((packed)) { ushort16 v; } ushort16_u;
typedef struct __attribute__((packed)) { char8 v; } char8_u;
typedef struct __attribute__((packed)) { uint8 v; } uint8_u;
typedef struct __attribute__((packed)) { uint v; } uint_u;
typedef struct __attribute__((packed)) { ulong v; } ulong_u;
#define LOAD_UC16(p) (((__global const uchar16_u *)(p))->v)
#define STORE_UC16(p, x) (((__global uchar16_u *)(p))->v = (x))
#define LOAD_US16(p) (((__global const ushort16_u *)(p))->v)
#define STORE_US16(p, x) (((__global ushort16_u *)(p))->v = (x))
#define STORE_C8(p, x) (((__global char8_u *)(p))->v = (x))
#define LOAD_W8(p) (((__global const uint8_u *)(p))->v)
#define STORE_W8(p, x) (((__global uint8_u *)(p))->v = (x))
#define STORE_U32(p, x) (((__global uint_u *)(p))->v = (x))
/* Bit counts: clang's builtins on PoCL (EMD_CLANG_BUILTINS, set by the host); OpenCL C
 * 1.2's own popcount and clz elsewhere (ctz is OpenCL 2.0: the lowest set bit's index from
 * clz of that bit alone), so the portable kernels need no clang extension. Arguments:
 * uint, nonzero for CTZ. */
#ifdef EMD_CLANG_BUILTINS
#define POPCOUNT(x) __builtin_popcount(x)
#define CTZ(x) __builtin_ctz(x)
#else
#define POPCOUNT(x) popcount(x)
#define CTZ(x) (31u - clz((x) & (0u - (x))))
#endif
/* PoCL 3.0 calls out of line for atomic_inc (a library call per increment); on PoCL the
 * host defines EMD_INLINE_ATOMICS and the compiler builtin becomes one `lock add`. */
#ifdef EMD_INLINE_ATOMICS
#define ATOMIC_INC(p) __sync_fetch_and_add((p), 1)
#define ATOMIC_ADD(p, v) __sync_fetch_and_add((p), (v))
#else
#define ATOMIC_INC(p) atomic_inc(p)
#define ATOMIC_ADD(p, v) atomic_add((p), (v))
#endif
#define CLAMPI(v, lo, hi) ((v) < (lo) ? (lo) : ((v) > (hi) ? (hi) : (v)))

inline int pos_mod(int a, int m) { int r = a % m; return r < 0 ? r + m : r; }

/* Pack 16 lane masks (all-ones = true) into the low 16 bits of a word. On PoCL for x86
 * the host defines EMD_X86_BUILTINS and this is one pmovmskb; the portable version
 * reduces the lanes with ORs. */
#if defined(EMD_X86_BUILTINS) && defined(__SSE2__)
typedef char emd_v16qi __attribute__((__vector_size__(16)));
inline uint pack16(short16 mask)
{
    return (uint)__builtin_ia32_pmovmskb128((emd_v16qi)convert_char16(mask)) & 0xFFFFu;
}
#else
inline uint pack16(short16 mask)
{
    const ushort16 bit = (ushort16)(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048,
                                    4096, 8192, 16384, 32768);
    ushort16 b = as_ushort16(mask) & bit;
    ushort8 a8 = b.lo | b.hi;
    ushort4 a4 = a8.lo | a8.hi;
    ushort2 a2 = a4.lo | a4.hi;
    return (uint)(a2.x | a2.y);
}
#endif
/* ---- states/prefilter helpers ---- */
/* Unsigned saturating subtraction and addition and a 32-lane mask pack. On x86 with AVX2
 * these are vpsubusw, vpaddusw and vpacksswb + vpermq + vpmovmskb (one pack for both
 * 16-lane halves); the portable versions use selects and pack16. The saturating x86
 * builtins left clang in LLVM 15 (Debian 12's PoCL 3.1) for the generic elementwise
 * ones, which compile to the same instructions: whichever the compiler has is used. */
#ifndef __has_builtin
#define __has_builtin(x) 0
#endif
#if defined(EMD_X86_BUILTINS) && defined(__AVX2__) && __has_builtin(__builtin_ia32_pmovmskb256) \
    && __has_builtin(__builtin_ia32_packsswb256) \
    && ((__has_builtin(__builtin_ia32_psubusb256) && __has_builtin(__builtin_ia32_psubusw256) \
         && __has_builtin(__builtin_ia32_paddusw256)) \
        || (__has_builtin(__builtin_elementwise_sub_sat) && __has_builtin(__builtin_elementwise_add_sat)))
typedef short emd_v16hi __attribute__((__vector_size__(32)));
typedef char emd_v32qi __attribute__((__vector_size__(32)));
typedef uchar emd_v32qu __attribute__((__vector_size__(32)));
typedef long emd_v4di __attribute__((__vector_size__(32)));
typedef struct __attribute__((packed)) { emd_v32qu v; } emd_v32qu_u;
#if __has_builtin(__builtin_ia32_psubusb256)
#define EMD_SUBS_U8X32(a, b) ((emd_v32qu)__builtin_ia32_psubusb256((emd_v32qi)(a), (emd_v32qi)(b)))
#define EMD_SUBS_U16(a, b) __builtin_astype(__builtin_ia32_psubusw256(__builtin_astype(a, emd_v16hi), \
                                                                      __builtin_astype(b, emd_v16hi)), ushort16)
#define EMD_ADDS_U16(a, b) __builtin_astype(__builtin_ia32_paddusw256(__builtin_astype(a, emd_v16hi), \
                                                                      __builtin_astype(b, emd_v16hi)), ushort16)
#else
#define EMD_SUBS_U8X32(a, b) __builtin_elementwise_sub_sat((a), (b))
#define EMD_SUBS_U16(a, b) __builtin_elementwise_sub_sat((a), (b))
#define EMD_ADDS_U16(a, b) __builtin_elementwise_add_sat((a), (b))
#endif
/* bit l = (now[l] - then[l] > T) for 32 bytes: sat(sat(now - T) - then) != 0 (vpsubusb,
 * vpcmpeqb, vpmovmskb: 32 pixels per instruction, no widening to 16 bits) */
inline uint exceeds32(__global const uchar *now, __global const uchar *then, uchar T)
{
    const emd_v32qu a = ((__global const emd_v32qu_u *)now)->v;
    const emd_v32qu b = ((__global const emd_v32qu_u *)then)->v;
    const emd_v32qu zero = {};
    const emd_v32qu d = EMD_SUBS_U8X32(EMD_SUBS_U8X32(a, zero + T), b);
    return ~(uint)__builtin_ia32_pmovmskb256((emd_v32qi)(d == zero));
}
inline ushort16 subs_u16(ushort16 a, ushort16 b) { return EMD_SUBS_U16(a, b); }
inline ushort16 adds_u16(ushort16 a, ushort16 b) { return EMD_ADDS_U16(a, b); }
/* bit l of the result = lane l of lo, bit 16 + l = lane l of hi (masks all-ones = true) */
inline uint pack32(short16 lo, short16 hi)
{
    const emd_v32qi p = __builtin_ia32_packsswb256(__builtin_astype(lo, emd_v16hi),
                                                   __builtin_astype(hi, emd_v16hi));
    const emd_v4di q = __builtin_astype(p, emd_v4di);
    return (uint)__builtin_ia32_pmovmskb256(
        __builtin_astype(__builtin_shufflevector(q, q, 0, 2, 1, 3), emd_v32qi));
}
#else
inline ushort16 subs_u16(ushort16 a, ushort16 b) { return a > b ? a - b : (ushort16)(0); }
inline ushort16 adds_u16(ushort16 a, ushort16 b) { return a + b < a ? (ushort16)(65535) : a + b; }
inline uint pack32(short16 lo, short16 hi) { return pack16(lo) | (pack16(hi) << 16); }
inline uint exceeds32(__global const uchar *now, __global const uchar *then, uchar T)
{
    const short16 d0 = convert_short16(LOAD_UC16(now)) - convert_short16(LOAD_UC16(then));
    const short16 d1 = convert_short16(LOAD_UC16(now + 16)) - convert_short16(LOAD_UC16(then + 16));
    return pack32(d0 > (short)T, d1 > (short)T);
}
#endif
/* bits [lo, hi] of a 32-bit word (empty if hi < lo; both may lie outside 0..31) */
inline uint bit_range(int lo, int hi)
{
    lo = lo < 0 ? 0 : lo;
    hi = hi > 31 ? 31 : hi;
    return hi < lo ? 0u : ((0xFFFFFFFFu >> (31 - hi)) & (0xFFFFFFFFu << lo));
}
/* ---- end ---- */
