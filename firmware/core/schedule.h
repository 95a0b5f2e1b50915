/* The measurement order of docs/physics.md (#measurement-order): the pair list of one or two rings,
 * and for each drive pair in list order every pair sharing no electrode with it, in list order. */
#ifndef CSTOMO_SCHEDULE_H
#define CSTOMO_SCHEDULE_H

#include <stdbool.h>
#include <stdint.h>

#include "cstomo_protocol.h"

typedef struct {
    uint8_t layers;                                   /* 1: one ring of 16; 2: two rings of 8 */
    uint8_t pair[CSTOMO_N_PAIRS][2];                  /* adjacent pairs, 0-based electrodes */
    uint8_t measure[CSTOMO_N_PAIRS][CSTOMO_N_MEASURE]; /* per drive pair: indices into pair[] */
} schedule_t;

/* Fill `s` for `layers` (1 or 2); false (s untouched) for any other value. */
bool schedule_build(schedule_t *s, uint8_t layers);
/* Value index 0..207 of drive pair d and its j-th measurement pair: d * 13 + j. */
static inline unsigned schedule_index(unsigned d, unsigned j) { return d * CSTOMO_N_MEASURE + j; }

#endif
