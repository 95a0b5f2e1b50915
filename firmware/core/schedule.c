#include "schedule.h"

bool schedule_build(schedule_t *s, uint8_t layers) {
    if (layers != CSTOMO_PATTERN_ONE_RING && layers != CSTOMO_PATTERN_TWO_RINGS)
        return false;
    const unsigned ring = CSTOMO_N_ELECTRODES / layers;
    s->layers = layers;
    for (unsigned e = 0; e < CSTOMO_N_PAIRS; e++) {
        s->pair[e][0] = (uint8_t)e;
        s->pair[e][1] = (uint8_t)((e / ring) * ring + (e % ring + 1) % ring);
    }
    for (unsigned d = 0; d < CSTOMO_N_PAIRS; d++) {
        unsigned j = 0;
        for (unsigned m = 0; m < CSTOMO_N_PAIRS; m++) {
            const uint8_t *a = s->pair[d], *b = s->pair[m];
            if (a[0] == b[0] || a[0] == b[1] || a[1] == b[0] || a[1] == b[1])
                continue;
            if (j < CSTOMO_N_MEASURE)
                s->measure[d][j] = (uint8_t)m;
            j++;
        }
        /* both patterns leave exactly 13 (16 - the pair itself - its two neighbours) */
    }
    return true;
}
