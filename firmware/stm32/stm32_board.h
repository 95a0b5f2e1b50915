/* The STM32 build's pieces besides the HAL: clocks and pins, the table front-end, the debug console. */
#ifndef CSTOMO_STM32_BOARD_H
#define CSTOMO_STM32_BOARD_H
#include <stdint.h>

void stm32_init(void);
void debug_write(const char *s);

/* the frames table in the image (frames_table.c, written by tools/frames_to_c.py) */
extern const float cstomo_frames[][208];
extern const uint32_t cstomo_n_frames;
extern const uint8_t cstomo_frames_layers;
extern const float cstomo_noise_v;

/* the table front-end: a sweep starts at drive (source, sink); the value of the selected electrodes */
void frontend_sweep(uint8_t source, uint8_t sink);
float frontend_value(uint8_t source, uint8_t sink, uint8_t pos, uint8_t neg);

#endif
