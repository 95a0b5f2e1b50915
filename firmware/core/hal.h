/* The hardware abstraction the portable core (board.c) runs on: one implementation per target
 * (host/hal_host.c: a POSIX process on a pseudo-terminal; stm32/hal_stm32.c: a Cortex-M4F).
 * Electrodes are 0-based (electrode 1 of the documents is 0). Nothing here allocates. */
#ifndef CSTOMO_HAL_H
#define CSTOMO_HAL_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

/* --- analog front-end ---------------------------------------------------------------------- */
/* Route the current source: +I into electrode `source`, out of `sink` (the drive multiplexers). */
void hal_select_drive(uint8_t source, uint8_t sink);
/* Route the instrumentation amplifier: + input to electrode `pos`, - input to `neg`. */
void hal_select_measure(uint8_t pos, uint8_t neg);
/* Wait until the multiplexers, the current source and the amplifier have settled after a switch
 * (`drive_changed`: the current path switched too, which settles longer). */
void hal_settle(bool drive_changed);
/* One differential sample V(pos) - V(neg) in volts at the ADC input referred back to the electrodes;
 * `*saturated` is set when the amplifier or the ADC was at its full scale (the value is then clipped). */
float hal_read_sample(bool *saturated);
/* The current source: on/off and its set point in amperes (false: the source cannot give it). */
void hal_current_on(bool on);
bool hal_current_set(float amps);
/* Contact check of one electrode (e.g. its lead-off comparator, or a small test current): true = good. */
bool hal_contact_ok(uint8_t electrode);

/* --- time ---------------------------------------------------------------------------------- */
/* Monotonic microseconds since power-up (64 bits: never wraps in practice). */
uint64_t hal_micros(void);

/* --- link (UART, USB CDC, or a pseudo-terminal) --------------------------------------------- */
/* Bytes received since the last call, up to `cap`; 0 when none (never blocks). */
size_t hal_link_read(uint8_t *buf, size_t cap);
/* Room in the transmit queue in bytes: a whole packet is written only when it fits. */
size_t hal_link_tx_room(void);
/* Queue `n` bytes for sending (n <= hal_link_tx_room()); returns the bytes queued. */
size_t hal_link_write(const uint8_t *buf, size_t n);
/* Let the link move bytes (drain the transmit queue as far as the line takes them; never blocks). */
void hal_link_poll(void);
/* True once after the link was (re)connected: the core goes idle (docs/protocol.md, 1.7). */
bool hal_link_reconnected(void);

#endif
