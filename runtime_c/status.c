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
};

typedef char pc_status_table_is_complete[
    (sizeof pc_status_names / sizeof pc_status_names[0] == PC_STATUS_COUNT) ? 1 : -1];

const char *pc_status_name(pc_status status)
{
    if ((int)status < 0 || status >= PC_STATUS_COUNT || !pc_status_names[status])
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
    vsnprintf(err->message, sizeof err->message, fmt, ap);
    va_end(ap);
    return status;
}
