/* Status names: one table, designated initialisers so a new code cannot be forgotten
 * silently (the size check below fails the build). */
#include "base.h"

#include <stdarg.h>

static const char *const pc_status_names[PC_STATUS_COUNT] = {
    [PC_OK] = "ok",
    [PC_ERR_ARGUMENT] = "invalid argument",
    [PC_ERR_IO] = "I/O error",
    [PC_ERR_MEMORY] = "out of memory",
    [PC_ERR_TRUNCATED] = "truncated file",
    [PC_ERR_MALFORMED] = "malformed model",
    [PC_ERR_UNSUPPORTED] = "unsupported feature",
    [PC_ERR_CONTRACT] = "model violates the pose contract",
    [PC_ERR_GRAPH] = "invalid graph",
    [PC_ERR_SHAPE] = "shape or type mismatch",
    [PC_ERR_NONFINITE] = "non-finite input",
    [PC_ERR_RUNTIME] = "runtime error",
    [PC_ERR_RANGE] = "pose outside the fitted range",
    [PC_ERR_QUATERNION] = "quaternion not unit",
    [PC_ERR_INTEGRITY] = "model file changed or unsigned",
};

typedef char pc_status_table_is_complete[
    (sizeof pc_status_names / sizeof pc_status_names[0] == PC_STATUS_COUNT) ? 1 : -1];

const char *pc_status_name(pc_status status)
{
    /* unsigned: the enum may be unsigned and one byte wide (arm-none-eabi's short enums) */
    if ((unsigned)status >= (unsigned)PC_STATUS_COUNT || !pc_status_names[status])
        return "unknown status";
    return pc_status_names[status];
}

pc_status pc_fail(pc_error *err, pc_status status, const char *fmt, ...)
{
    va_list ap;
    if (!err)
        return status;
    err->status = status;
    va_start(ap, fmt);
    pc_vformat(err->message, sizeof err->message, fmt, ap);
    va_end(ap);
    return status;
}

/* The message formatter. The library's messages use printf's integer and string
 * conversions only, and are formatted here rather than by the C library: newlib-nano (the
 * C library of a Cortex-M firmware) has no %zu or %ll, so its vsnprintf would print "byte
 * zu" and shift every argument after it. Here a message reads the same on every target.
 * Handled: %% %c %s (precision N or *), %d %i %u %x with no, l, ll or z length. Width and
 * flags are not (tests/test_runtime_layers.py refuses other conversions in the sources). */
typedef struct pc_out {
    char *buf;
    size_t size, len;
} pc_out;

static void pc_put(pc_out *o, char c)
{
    if (o->len + 1 < o->size)
        o->buf[o->len] = c;
    o->len++;
}

static void pc_put_unsigned(pc_out *o, unsigned long long v, unsigned base, int negative)
{
    char digits[24];
    int n = 0;
    do {
        digits[n++] = "0123456789abcdef"[v % base];
        v /= base;
    } while (v);
    if (negative)
        pc_put(o, '-');
    while (n)
        pc_put(o, digits[--n]);
}

static void pc_put_signed(pc_out *o, long long v)
{
    /* -(v + 1) + 1: no overflow for LLONG_MIN */
    if (v < 0)
        pc_put_unsigned(o, (unsigned long long)(-(v + 1)) + 1u, 10, 1);
    else
        pc_put_unsigned(o, (unsigned long long)v, 10, 0);
}

/* A conversion's precision (-1: none; ".*" takes it from the arguments) and length
 * (1: l, 2: ll, 3: z); returns where its conversion character is. The va_list goes by
 * pointer: C99 leaves one passed by value indeterminate in the caller once used. */
static const char *pc_read_spec(const char *fmt, va_list *ap, int *precision, int *length)
{
    *precision = -1;
    *length = 0;
    if (*fmt == '.') {
        fmt++;
        if (*fmt == '*') {
            *precision = va_arg(*ap, int);
            fmt++;
        } else {
            for (*precision = 0; *fmt >= '0' && *fmt <= '9'; fmt++)
                *precision = *precision * 10 + (*fmt - '0');
        }
    }
    if (*fmt == 'z') {
        *length = 3;
        fmt++;
    } else {
        for (; *fmt == 'l' && *length < 2; fmt++)
            (*length)++;
    }
    return fmt;
}

/* One conversion of the subset, its argument taken from ap; returns 0 for a character that
 * is none (shown as is by the caller, nothing consumed). */
static int pc_convert(pc_out *o, char conv, int precision, int length, va_list *ap)
{
    switch (conv) {
    case 'd': case 'i':
        pc_put_signed(o, length == 2 ? va_arg(*ap, long long)
                         : length == 1 ? (long long)va_arg(*ap, long)
                         : length == 3 ? (long long)va_arg(*ap, ptrdiff_t)
                                       : (long long)va_arg(*ap, int));
        return 1;
    case 'u': case 'x':
        pc_put_unsigned(o, length == 2 ? va_arg(*ap, unsigned long long)
                           : length == 1 ? (unsigned long long)va_arg(*ap, unsigned long)
                           : length == 3 ? (unsigned long long)va_arg(*ap, size_t)
                                         : (unsigned long long)va_arg(*ap, unsigned),
                        conv == 'x' ? 16u : 10u, 0);
        return 1;
    case 's': {
        const char *str = va_arg(*ap, const char *);
        int k;
        if (!str)
            str = "(null)";
        /* the precision first: a %.*s slice need not be terminated, so its end is not read */
        for (k = 0; (precision < 0 || k < precision) && str[k]; k++)
            pc_put(o, str[k]);
        return 1;
    }
    case 'c':
        pc_put(o, (char)va_arg(*ap, int));
        return 1;
    case '%':
        pc_put(o, '%');
        return 1;
    default:
        return 0;
    }
}

void pc_vformat(char *buf, size_t size, const char *fmt, va_list ap)
{
    pc_out o;
    va_list args;
    o.buf = buf;
    o.size = size;
    o.len = 0;
    if (!size)
        return;
    va_copy(args, ap);
    for (; *fmt; fmt++) {
        int precision, length;
        if (*fmt != '%') {
            pc_put(&o, *fmt);
            continue;
        }
        fmt = pc_read_spec(fmt + 1, &args, &precision, &length);
        if (pc_convert(&o, *fmt, precision, length, &args))
            continue;
        /* not a conversion of the subset: shown as is, nothing consumed */
        pc_put(&o, '%');
        if (!*fmt)
            fmt--;
        else
            pc_put(&o, *fmt);
    }
    va_end(args);
    o.buf[o.len < o.size ? o.len : o.size - 1] = '\0';
}

void pc_format(char *buf, size_t size, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    pc_vformat(buf, size, fmt, ap);
    va_end(ap);
}
