/* The few STM32F4 registers the firmware touches (RM0090), without a vendor SDK. */
#ifndef CSTOMO_STM32F4_H
#define CSTOMO_STM32F4_H
#include <stdint.h>

#define REG(addr) (*(volatile uint32_t *)(addr))

/* core */
#define SCB_CPACR REG(0xE000ED88u)
#define SCB_ICSR REG(0xE000ED04u)
#define NVIC_ISER(n) REG(0xE000E100u + 4u * (n))
#define DWT_CTRL REG(0xE0001000u)
#define DWT_CYCCNT REG(0xE0001004u)
#define DEMCR REG(0xE000EDFCu)

/* reset and clock control */
#define RCC_BASE 0x40023800u
#define RCC_CR REG(RCC_BASE + 0x00u)
#define RCC_PLLCFGR REG(RCC_BASE + 0x04u)
#define RCC_CFGR REG(RCC_BASE + 0x08u)
#define RCC_AHB1ENR REG(RCC_BASE + 0x30u)
#define RCC_APB1ENR REG(RCC_BASE + 0x40u)
#define RCC_APB2ENR REG(RCC_BASE + 0x44u)
#define FLASH_ACR REG(0x40023C00u)

/* TIM2 (32 bits, on APB1): the microsecond clock */
#define TIM2_BASE 0x40000000u
#define TIM_CR1(b) REG((b) + 0x00u)
#define TIM_EGR(b) REG((b) + 0x14u)
#define TIM_CNT(b) REG((b) + 0x24u)
#define TIM_PSC(b) REG((b) + 0x28u)
#define TIM_ARR(b) REG((b) + 0x2Cu)
#define TIM_CR1_CEN (1u << 0)
#define TIM_EGR_UG (1u << 0)

/* GPIO */
#define GPIOA_BASE 0x40020000u
#define GPIOB_BASE 0x40020400u
#define GPIOC_BASE 0x40020800u
#define GPIO_MODER(b) REG((b) + 0x00u)
#define GPIO_OSPEEDR(b) REG((b) + 0x08u)
#define GPIO_IDR(b) REG((b) + 0x10u)
#define GPIO_BSRR(b) REG((b) + 0x18u)
#define GPIO_AFRL(b) REG((b) + 0x20u)
#define GPIO_AFRH(b) REG((b) + 0x24u)

/* USART1 (the link, PA9 TX / PA10 RX) and USART2 (a debug console, PA2 / PA3) */
#define USART1_BASE 0x40011000u
#define USART2_BASE 0x40004400u
#define USART_SR(b) REG((b) + 0x00u)
#define USART_DR(b) REG((b) + 0x04u)
#define USART_BRR(b) REG((b) + 0x08u)
#define USART_CR1(b) REG((b) + 0x0Cu)
#define USART_SR_RXNE (1u << 5)
#define USART_SR_TXE (1u << 7)
#define USART_SR_ORE (1u << 3)
#define USART_CR1_UE (1u << 13)
#define USART_CR1_TE (1u << 3)
#define USART_CR1_RE (1u << 2)
#define USART_CR1_RXNEIE (1u << 5)
#define USART1_IRQ 37u

/* SPI1: the ADC (ADS8860: PA5 SCK, PA6 MISO, PA7 MOSI; PC0 CONVST) */
#define SPI1_BASE 0x40013000u
#define SPI_CR1(b) REG((b) + 0x00u)
#define SPI_SR(b) REG((b) + 0x08u)
#define SPI_DR(b) REG((b) + 0x0Cu)
#define SPI_SR_RXNE (1u << 0)

/* DAC channel 1 on PA4: the Howland source's set point */
#define DAC_BASE 0x40007400u
#define DAC_CR REG(DAC_BASE + 0x00u)
#define DAC_DHR12R1 REG(DAC_BASE + 0x08u)

#endif
