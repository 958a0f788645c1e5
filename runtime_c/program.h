/* Layer 8, planner: one-pose programs. At N = 1 the exporter's quaternion, matrix and
 * Gram-Schmidt subgraphs are hundreds of nodes over 1 to 9 elements, each costing more to
 * launch than to compute: each run of such nodes becomes one k_scalar_program launch,
 * built while the graph is streamed. */
#ifndef PC_PROGRAM_H
#define PC_PROGRAM_H

#include "place.h"

/* Sizes of the program under construction. Larger programs launch fewer steps; the
 * compiler's working memory grows with them. */
typedef struct pc_program_limits {
    size_t ops;         /* element operations of one program (before dead ones go) */
    int interpret;      /* never a compiled program (PC_LOAD_INTERPRET) */
} pc_program_limits;

/* State for a one-pose plan's programs (keep end of the scratch, for the pass). */
pc_status pc_program_start(pc_pass *pp, const pc_program_limits *limits);
/* Can node p (prepared for this plan) run as element operations of a program? */
int pc_program_takes(const pc_pass *pp, const pc_prep *p);
/* Appends p's elements to the open program (opening one): its output records get
 * element maps instead of blocks. */
pc_status pc_program_expand(pc_pass *pp, const pc_prep *p);
/* Closes the open program, if any: values read after it get blocks, the operations that
 * compute them are kept, ordered and written as one step. */
pc_status pc_program_close(pc_pass *pp);

#endif
