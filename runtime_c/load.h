/* Layer 9, loading: scan -> plan -> load-time checks, the one path behind
 * every pc_load_* entry point (and the conformance-test entry, testing.c). */
#ifndef PC_LOAD_H
#define PC_LOAD_H

#include "model.h"

/* any_io: accept any input and output names of static shape (tests only). buf: the
 * caller's memory for scratch and arena (NULL: malloc). *scratch_used (may be NULL):
 * scratch bytes the load took. */
pc_status pc_load_impl(const void *data, size_t size, const pc_options *opts, int any_io,
                       void *buf, size_t buf_size, pc_model **model, size_t *scratch_used,
                       pc_error *err);

#endif
