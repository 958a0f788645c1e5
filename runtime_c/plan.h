/* Layer 8, planner: static plans for batches of 1, 16, 256, ... and max_batch (shapes,
 * kernel choice, buffer offsets by liveness) packed with the constants into one arena. */
#ifndef PC_PLAN_H
#define PC_PLAN_H

#include "model.h"
#include "op.h"

/* Plans b (after the graph scan) into an arena: malloc'd when buf is NULL, else placed at the
 * end of buf[0, buf_size), whose start holds b's scratch. */
pc_status pc_plan_build(pc_builder *b, const pc_options *opts, void *buf, size_t buf_size,
                        pc_model **model);

#endif
