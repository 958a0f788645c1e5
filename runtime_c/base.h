/* Layer 0, base: what every file of the library shares (status messages, limits). */
#ifndef PC_BASE_H
#define PC_BASE_H

#include "posecorr.h"

#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>

#define PC_MAX_RANK 6
/* The optional second input of the pose contract: float32 [N], s since the session's start. */
#define PC_TIME_INPUT "t"
/* Alignment of every load-time allocation and arena region: an AVX register where the
 * dense kernels have AVX copies, a double elsewhere (small targets count their bytes). */
#if defined(__x86_64__) || defined(_M_X64)
#define PC_ALIGN 32
#else
#define PC_ALIGN 8
#endif

/* A function whose large frame must not add to its caller's (the deepest call chain is
 * what a small target's stack must hold). */
#if defined(__GNUC__)
#define PC_NOINLINE __attribute__((noinline))
#else
#define PC_NOINLINE
#endif

/* Inlined wherever it is called: a kernel's AVX2 copy then really runs AVX2 loops
 * (dense.c), and pc_run's one-pose path is one function with one prologue (run.c). */
#ifdef __GNUC__
#define PC_INLINE static inline __attribute__((always_inline))
#else
#define PC_INLINE static inline
#endif

/* A function of the one-pose path. GCC and Clang put these in .text.hot, which the linker
 * keeps together: the code a pose runs spans a few pages instead of the library's width.
 * Not in a build for size (the firmware): there `hot` would also optimise for speed, at
 * 3.8 KB of flash, and a microcontroller has no pages. */
#if defined(__GNUC__) && !defined(__OPTIMIZE_SIZE__)
#define PC_HOT __attribute__((hot))
#else
#define PC_HOT
#endif

/* A function only a failure reaches: out of the hot pages, and the branches to it are
 * laid out as the unlikely ones. */
#if defined(__GNUC__)
#define PC_RARE __attribute__((cold, noinline))
#else
#define PC_RARE
#endif

/* Fills err (may be NULL) with status and a printf-style message; returns status. */
pc_status pc_fail(pc_error *err, pc_status status, const char *fmt, ...)
#ifdef __GNUC__
    __attribute__((format(printf, 3, 4)))
#endif
    ;

/* snprintf for the library's messages (status.c: the same text on every C library). A
 * message is written only on a failure, so a call is the unlikely branch (cold). */
void pc_format(char *buf, size_t size, const char *fmt, ...)
#ifdef __GNUC__
    __attribute__((format(printf, 3, 4), cold))
#endif
    ;
void pc_vformat(char *buf, size_t size, const char *fmt, va_list ap);

/* CRC-32C of size bytes continuing crc (0 to start): crc32c.c. */
uint32_t pc_crc32c(uint32_t crc, const void *data, size_t size);

/* Largest element count of a tensor: its bytes (at most 8 per element), rounded up, fit
 * a size_t of either width (2^31 - 1 where size_t has 64 bits, 2^28 - 1 with 32). */
#define PC_MAX_ELEMENTS ((size_t)(SIZE_MAX / 16 < 0x7fffffffu ? SIZE_MAX / 16 : 0x7fffffffu))

/* *count *= d when d >= 0 and the product stays <= limit; returns 0 (count unchanged)
 * otherwise. d is compared in 64 bits, so a dimension beyond a 32-bit size_t fails
 * rather than wrapping. */
static inline int pc_mul_count(size_t *count, int64_t d, size_t limit)
{
    if (d < 0 || (d > 0 && (uint64_t)*count > (uint64_t)limit / (uint64_t)d))
        return 0;
    *count *= (size_t)d;
    return 1;
}

static inline size_t pc_round(size_t x)
{
    return (x + PC_ALIGN - 1) / PC_ALIGN * PC_ALIGN;
}

#endif
