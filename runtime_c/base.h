/* Layer 0, base: what every file of the library shares (status messages, limits). */
#ifndef PC_BASE_H
#define PC_BASE_H

#include "posecorr.h"

#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>

#define PC_MAX_RANK 6
#define PC_ALIGN 32

/* Fills err (may be NULL) with status and a printf-style message; returns status. */
pc_status pc_fail(pc_error *err, pc_status status, const char *fmt, ...)
#ifdef __GNUC__
    __attribute__((format(printf, 3, 4)))
#endif
    ;

static inline size_t pc_round(size_t x)
{
    return (x + PC_ALIGN - 1) / PC_ALIGN * PC_ALIGN;
}

#endif
