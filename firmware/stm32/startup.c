/* the range initialisers of GCC fill the table; the named entries then override them */
#pragma GCC diagnostic ignored "-Woverride-init"
/* Reset and vector table of an STM32F4 (Cortex-M4F): copy .data, clear .bss, enable the FPU, main. */
#include <stdint.h>
#include <string.h>

#include "stm32f4.h"

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
int main(void);
void reset_handler(void);
void usart1_handler(void);

static void default_handler(void) {
    for (;;) {
    }
}

void nmi_handler(void) __attribute__((weak, alias("default_handler")));
void hardfault_handler(void) __attribute__((weak, alias("default_handler")));

#define N_VECTORS (16 + 82)
__attribute__((section(".isr_vector"), used)) static void (*const vectors[N_VECTORS])(void) = {
    [0] = (void (*)(void))(uintptr_t)&_estack,
    [1] = reset_handler,
    [2] = nmi_handler,
    [3] = hardfault_handler,
    [4] = default_handler, /* MemManage */
    [5] = default_handler, /* BusFault */
    [6] = default_handler, /* UsageFault */
    [11] = default_handler, /* SVCall */
    [14] = default_handler, /* PendSV */
    [7 ... 10] = default_handler,
    [12 ... 13] = default_handler,
    [15] = default_handler, /* SysTick: unused (TIM2 is the clock) */
    [16 ... N_VECTORS - 1] = default_handler,
    [16 + USART1_IRQ] = usart1_handler,
};

void reset_handler(void) {
    memcpy(&_sdata, &_sidata, (size_t)((char *)&_edata - (char *)&_sdata));
    memset(&_sbss, 0, (size_t)((char *)&_ebss - (char *)&_sbss));
    SCB_CPACR |= 0xFu << 20; /* CP10, CP11: the FPU */
    __asm volatile("dsb\n isb");
    main();
    for (;;) {
    }
}
