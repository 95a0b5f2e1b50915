/* The HAL on an STM32F4 (Cortex-M4F, 168 MHz), register level (docs/firmware.md has the wiring):
 *   PB0..3 drive source mux, PB4..7 drive sink mux, PB8..11 measure + mux, PB12..15 measure - mux
 *   (4 x 16:1 multiplexers, one BSRR write switches all four); PC1 multiplexer enable;
 *   PA4 DAC1: the Howland source's set point (8 mA at 0.8 V over a 100 ohm sense resistor);
 *   SPI1 + PC0 CONVST: the ADC (ADS8860, 16 bits, after an AD8421 in-amp);
 *   PC2..PC5 + PC6..PC9: lead-off comparators of the electrodes, read as one port (contact check);
 *   USART1 PA9/PA10: the link (RX by interrupt into a ring, TX drained from a ring while waiting);
 *   USART2 PA2: a debug console (board_debug_line); TIM2: the microsecond clock (free-running at 1 MHz,
 *   32 bits, extended to 64 in hal_micros; no interrupt).
 * With CSTOMO_FRONTEND_TABLE (the emulated build, QEMU has no analog world) the sample is read from
 * a table of frames in the image (frames_table.c) plus noise, and the contact check passes; the
 * multiplexer, DAC and CONVST writes still go to their registers. */
#include <stdbool.h>
#include <stdint.h>

#include "../core/cstomo_protocol.h"
#include "../core/hal.h"
#include "stm32f4.h"
#include "stm32_board.h"

/* TIM2's prescaler for 1 MHz. On the part TIM2 counts at 2 x PCLK1 = 84 MHz (APB1 at 168/4 = 42 MHz,
 * its timers doubled because APB1's prescaler is not 1): 84 MHz / (83 + 1). QEMU's netduinoplus2
 * (stm32f405_soc, hw/timer/stm32f2xx_timer.c) counts its timers at a fixed "clock-frequency" of 1 GHz
 * taken from QEMU_CLOCK_VIRTUAL (the host's clock while the machine runs) whatever RCC says:
 * 1 GHz / (999 + 1). docs/firmware.md, "The clock". */
#ifdef CSTOMO_FRONTEND_TABLE
#define TIM2_PSC 999u
#else
#define TIM2_PSC 83u
#endif
#define SETTLE_DRIVE_US 20u /* current source and drive mux after a drive switch */
#define SETTLE_MEASURE_US 2u /* measure mux + in-amp (AD8421: 0.8 us to 0.01 %) */
#define FULL_SCALE_V 2.5f
#define TX_RING 2048u /* two frames */
#define RX_RING 256u

static uint8_t tx_ring[TX_RING];
static uint32_t tx_head, tx_tail;
static volatile uint8_t rx_ring[RX_RING];
static volatile uint32_t rx_head;
static uint32_t rx_tail;
static float current_a = CSTOMO_DRIVE_CURRENT_A;
static bool current_on;
static uint8_t sel_src, sel_sink, sel_pos, sel_neg;

/* --- clocks and pins ------------------------------------------------------------------------ */
static void wait_flag(volatile uint32_t *reg, uint32_t mask) {
    for (uint32_t i = 0; i < 100000u && !(*reg & mask); i++) { /* bounded: an emulator may not set it */
    }
}

void stm32_init(void) {
    /* 168 MHz from the 8 MHz crystal: PLL M=8 N=336 P=2 Q=7; flash 5 wait states; APB1 /4, APB2 /2 */
    RCC_CR |= 1u << 16; /* HSEON */
    wait_flag(&RCC_CR, 1u << 17);
    RCC_PLLCFGR = 8u | (336u << 6) | (0u << 16) | (1u << 22) | (7u << 24);
    RCC_CR |= 1u << 24; /* PLLON */
    wait_flag(&RCC_CR, 1u << 25);
    FLASH_ACR = 5u | (1u << 8) | (1u << 9) | (1u << 10);
    RCC_CFGR = (5u << 10) | (4u << 13) | 2u; /* PPRE1 /4, PPRE2 /2, SW = PLL */
    RCC_AHB1ENR |= 0x7u;                      /* GPIOA, B, C */
    RCC_APB2ENR |= (1u << 4) | (1u << 12);    /* USART1, SPI1 */
    RCC_APB1ENR |= 1u | (1u << 17) | (1u << 29); /* TIM2, USART2, DAC */
    /* PA2 USART2 TX, PA9/PA10 USART1 (AF7), PA5..7 SPI1 (AF5), PA4 analog (DAC) */
    GPIO_MODER(GPIOA_BASE) = (GPIO_MODER(GPIOA_BASE) & ~0x003FFF30u) | (2u << 4) | (3u << 8) | (2u << 10) |
                             (2u << 12) | (2u << 14) | (2u << 18) | (2u << 20);
    GPIO_AFRL(GPIOA_BASE) = (7u << 8) | (5u << 20) | (5u << 24) | (5u << 28);
    GPIO_AFRH(GPIOA_BASE) = (7u << 4) | (7u << 8);
    GPIO_MODER(GPIOB_BASE) = 0x55555555u; /* PB0..15 outputs: the mux addresses */
    GPIO_OSPEEDR(GPIOB_BASE) = 0xAAAAAAAAu;
    GPIO_MODER(GPIOC_BASE) = (1u << 0) | (1u << 2); /* PC0 CONVST, PC1 mux enable; PC2..9 inputs */
    /* USART1 921600 baud at APB2 84 MHz (84e6 / 921600 = 91.1: mantissa 5, fraction 11), RX interrupt */
    USART_BRR(USART1_BASE) = (5u << 4) | 11u;
    USART_CR1(USART1_BASE) = USART_CR1_UE | USART_CR1_TE | USART_CR1_RE | USART_CR1_RXNEIE;
    NVIC_ISER(USART1_IRQ / 32u) = 1u << (USART1_IRQ % 32u);
    /* USART2 115200 at APB1 42 MHz: 22.79 -> mantissa 22, fraction 13 */
    USART_BRR(USART2_BASE) = (22u << 4) | 13u;
    USART_CR1(USART2_BASE) = USART_CR1_UE | USART_CR1_TE;
    /* SPI1 master, CPOL 0 CPHA 0, 16-bit frames, fPCLK/4 = 21 MHz */
    SPI_CR1(SPI1_BASE) = (1u << 2) | (1u << 3) | (1u << 6) | (1u << 8) | (1u << 9) | (1u << 11);
    DAC_CR = 1u; /* channel 1 on */
    /* TIM2: free-running up-counter at 1 MHz over its whole 32 bits; the update event (UG) loads the
     * prescaler, which is buffered on the part */
    TIM_PSC(TIM2_BASE) = TIM2_PSC;
    TIM_ARR(TIM2_BASE) = 0xFFFFFFFFu;
    TIM_EGR(TIM2_BASE) = TIM_EGR_UG;
    TIM_CR1(TIM2_BASE) = TIM_CR1_CEN;
}

void usart1_handler(void) {
    uint32_t sr = USART_SR(USART1_BASE);
    if (sr & (USART_SR_RXNE | USART_SR_ORE)) {
        uint8_t b = (uint8_t)USART_DR(USART1_BASE); /* reading DR clears RXNE and ORE */
        if (rx_head - rx_tail < RX_RING)
            rx_ring[rx_head++ % RX_RING] = b;
    }
}

/* TIM2's count extended to 64 bits: it wraps every 71.6 minutes and the main loop reads it far more
 * often than that (every frame, every poll). Main context only. */
uint64_t hal_micros(void) {
    static uint32_t last;
    static uint64_t high;
    uint32_t now = TIM_CNT(TIM2_BASE);
    if (now < last)
        high += (uint64_t)1 << 32;
    last = now;
    return high + now;
}

__attribute__((unused)) static void busy_wait_us(uint32_t us) {
    uint64_t until = hal_micros() + us;
    while (hal_micros() < until)
        hal_link_poll();
}

/* --- analog front-end ----------------------------------------------------------------------- */
static void mux_write(void) {
    uint32_t addr = (uint32_t)sel_src | ((uint32_t)sel_sink << 4) | ((uint32_t)sel_pos << 8) | ((uint32_t)sel_neg << 12);
    GPIO_BSRR(GPIOB_BASE) = addr | ((~addr & 0xFFFFu) << 16);
}

void hal_select_drive(uint8_t source, uint8_t sink) {
    sel_src = source & 15u;
    sel_sink = sink & 15u;
    mux_write();
    frontend_sweep(sel_src, sel_sink);
}

void hal_select_measure(uint8_t pos, uint8_t neg) {
    sel_pos = pos & 15u;
    sel_neg = neg & 15u;
    mux_write();
}

void hal_settle(bool drive_changed) {
#ifdef CSTOMO_FRONTEND_TABLE
    (void)drive_changed; /* no analog world to wait for; the link is served instead */
    hal_link_poll();
#else
    busy_wait_us(drive_changed ? SETTLE_DRIVE_US : SETTLE_MEASURE_US);
#endif
}

float hal_read_sample(bool *saturated) {
    float v;
#ifdef CSTOMO_FRONTEND_TABLE
    v = frontend_value(sel_src, sel_sink, sel_pos, sel_neg) * (current_a / CSTOMO_DRIVE_CURRENT_A);
    if (!current_on)
        v = 0.0f;
#else
    /* ADS8860: CONVST high starts the conversion (710 ns), then 16 bits out, two's complement,
     * +-FULL_SCALE_V after the in-amp */
    GPIO_BSRR(GPIOC_BASE) = 1u;
    for (volatile int i = 0; i < 120; i++) {
    }
    GPIO_BSRR(GPIOC_BASE) = 1u << 16;
    SPI_DR(SPI1_BASE) = 0;
    while (!(SPI_SR(SPI1_BASE) & SPI_SR_RXNE)) {
    }
    int16_t code = (int16_t)SPI_DR(SPI1_BASE);
    v = (float)code * (FULL_SCALE_V / 32768.0f);
    *saturated = code == 32767 || code == -32768;
#endif
    bool sat = v >= FULL_SCALE_V || v <= -FULL_SCALE_V;
    if (sat)
        v = v > 0 ? FULL_SCALE_V : -FULL_SCALE_V;
    *saturated = sat;
    return v;
}

void hal_current_on(bool on) {
    current_on = on;
    DAC_DHR12R1 = on ? (uint32_t)(current_a * 100.0f / 3.3f * 4095.0f) : 0u; /* 100 ohm sense, 3.3 V ref */
    GPIO_BSRR(GPIOC_BASE) = on ? 1u << 1 : 1u << 17;                          /* mux enable */
}

bool hal_current_set(float amps) {
    if (!(amps > 0.0f && amps <= 0.02f)) /* the DAC's range: 3.3 V over 100 ohm, the source's compliance */
        return false;
    current_a = amps;
    if (current_on)
        hal_current_on(true);
    return true;
}

bool hal_contact_ok(uint8_t electrode) {
#ifdef CSTOMO_FRONTEND_TABLE
    (void)electrode;
    return true;
#else
    /* lead-off comparators: one bit per electrode pair group on PC2..PC9 (low = contact) */
    return !(GPIO_IDR(GPIOC_BASE) & (1u << (2u + electrode / 2u)));
#endif
}

/* --- link ----------------------------------------------------------------------------------- */
size_t hal_link_read(uint8_t *buf, size_t cap) {
    size_t n = 0;
    while (n < cap && rx_tail != rx_head)
        buf[n++] = rx_ring[rx_tail++ % RX_RING];
    return n;
}

size_t hal_link_tx_room(void) { return TX_RING - (tx_head - tx_tail); }

size_t hal_link_write(const uint8_t *buf, size_t n) {
    if (n > hal_link_tx_room())
        return 0;
    for (size_t i = 0; i < n; i++)
        tx_ring[tx_head++ % TX_RING] = buf[i];
    return n;
}

void hal_link_poll(void) {
    while (tx_tail != tx_head && (USART_SR(USART1_BASE) & USART_SR_TXE))
        USART_DR(USART1_BASE) = tx_ring[tx_tail++ % TX_RING];
}

bool hal_link_reconnected(void) { return false; }

void debug_write(const char *s) {
    for (; *s; s++) {
        while (!(USART_SR(USART2_BASE) & USART_SR_TXE)) {
        }
        USART_DR(USART2_BASE) = (uint8_t)*s;
    }
}
