/* Layer 5, graph passes on the IR: operator check, topological order, liveness,
 * constant folding and activation fusion. */
#ifndef PC_PASSES_H
#define PC_PASSES_H

#include "op.h"

pc_status pc_run_passes(pc_builder *b);

#endif
