/* Layer 6, the graph scan: everything about the graph that does not depend on the batch,
 * found once and kept in a few bytes per node and value for the plan passes: operators
 * known, names resolved into references, nodes in topological order, nodes that reach
 * no output dropped, initializer-only subgraphs folded into constants, constants the
 * operators derive computed, Gemm + Tanh/Sigmoid/Relu/Clip fused, the last reader of
 * every value and the most values alive at once. */
#ifndef PC_GRAPH_H
#define PC_GRAPH_H

#include "op.h"

pc_status pc_scan_graph(pc_builder *b);

/* The scan's view of input k of node n: the record of a constant when it is one (an
 * initializer or a folded output; *id = -1 otherwise). The record is taken from the
 * pool and must be released by the caller. */
pc_status pc_const_input(pc_builder *b, uint16_t ref, int end, int32_t *id);

#endif
