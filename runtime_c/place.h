/* Layer 8, planner: what one pass over the graph writes, and where. A plan is built twice
 * by the same code: a sizing pass counts the bytes of every part of the arena, then a
 * filling pass writes them into an arena of exactly that size. Here: the activation
 * blocks (first fit, freed after their last reader), the arena's regions, constants
 * placed once for all plans (or used where they lie in the file), and the steps. */
#ifndef PC_PLACE_H
#define PC_PLACE_H

#include "model.h"
#include "op.h"

/* An activation buffer shared by a value and the views of it. */
typedef struct pc_block {
    size_t off, size;
    int16_t refs;       /* records holding it; 0: free */
    uint8_t deferred;   /* released while a one-pose program still reads it */
} pc_block;

/* One part of the arena: its start (filling pass) and the bytes taken so far. */
typedef struct pc_region {
    uint8_t *base;
    size_t used;
} pc_region;

/* The arena's parts, in memory order. */
enum {
    PC_REGION_STEPS,    /* pc_step of every plan */
    PC_REGION_IO,       /* operand pointers of the steps */
    PC_REGION_PARAMS,   /* parameter blocks */
    PC_REGION_CONSTS,   /* constants copied out of the file */
    PC_REGION_KPOOL,    /* the one-pose programs' constants (just below the activations,
                         * so that program operands are offsets from one base) */
    PC_REGIONS
};

typedef struct pc_placed {
    int32_t key;
    size_t off;
} pc_placed;

struct pc_program;

typedef struct pc_pass {
    pc_builder *b;
    int fill;           /* 0: sizing pass, 1: filling pass */
    size_t batch;
    /* activations of the plan being built */
    pc_block *blocks;
    int32_t *live;      /* blocks in use, by offset */
    size_t cap_blocks, n_live, act_peak;
    int defer_frees;    /* a one-pose program is open: freed blocks stay until it closes */
    uint8_t *act_base;  /* filling pass */
    /* the arena */
    pc_region region[PC_REGIONS];
    pc_placed *placed;  /* constants copied so far, for all plans */
    size_t n_placed, cap_placed;
    /* the plan being built */
    pc_plan *plan;      /* filling pass: its entry in the model */
    size_t n_steps;
    pc_step *last_step; /* filling pass: the step an MLP layer may chain onto */
    int last_layer;     /* the last step is a chain of MLP layers (1 + its AVX2 flag) ... */
    int32_t last_out;   /* ... whose last output is this block */
    struct pc_program *prog; /* the one-pose program under construction (batch 1) */
    size_t kpool_total; /* filling pass: the programs' constant pool, all plans */
    /* the MLP-layer chain the last step is (extended in place) */
    size_t chain_io, chain_prm, chain_layers;
    int32_t *input_ids; /* records of the graph inputs */
    uint32_t in0, out0; /* the node being planned: its first input (in_ref), first output */
    size_t blocks_high; /* blocks a pass has taken at once, at most */
} pc_pass;

/* Bytes of a region's entry, so that both passes round the same way. */
size_t pc_region_round(size_t bytes);
/* size bytes of a region: a pointer into the arena (filling pass) or NULL (sizing pass,
 * where only the count matters). */
void *pc_region_take(pc_pass *pp, int region, size_t bytes);

/* Blocks: a new one of size bytes, placed first fit among those in use. */
pc_status pc_block_new(pc_pass *pp, size_t bytes, int32_t *block);
void pc_block_ref(pc_pass *pp, int32_t block);
void pc_block_unref(pc_pass *pp, int32_t block);
/* Frees the blocks released while a program was open. */
void pc_block_flush(pc_pass *pp);
/* Where a block is (filling pass). */
void *pc_block_at(const pc_pass *pp, int32_t block);

/* A record's storage as a run-time pointer (filling pass; NULL while sizing): its block,
 * or its constant, copied once into the arena unless it may be used where it lies. */
pc_status pc_locate(pc_pass *pp, const pc_value *v, void **at);
/* A new block for record id (its count and type), unless it is a constant. */
pc_status pc_give_block(pc_pass *pp, int32_t id);
/* Releases record id and its hold on its block. */
void pc_drop(pc_pass *pp, int32_t id);

/* Appends a step of fn over the records ids (inputs then outputs, -1 for absent) with a
 * copy of the parameter block. */
pc_status pc_emit_step(pc_pass *pp, pc_kernel_fn fn, const int32_t *ids, size_t n_ids,
                       const void *prm, size_t prm_size, size_t n);

#endif
