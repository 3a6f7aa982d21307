/* Reset and vector table of the SAM3X8E for the size build: copy .data, clear .bss, run the C++ static
 * constructors, call main(). Only the entries this image uses are filled in. */
#include <stdint.h>

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
extern int main(void);
extern void __libc_init_array(void);
void SysTick_Handler(void);

void Reset_Handler(void) {
  uint32_t* src = &_sidata;
  for (uint32_t* dst = &_sdata; dst < &_edata;) *dst++ = *src++;
  for (uint32_t* dst = &_sbss; dst < &_ebss;) *dst++ = 0;
  __libc_init_array();
  main();
  for (;;) {
  }
}

static void Default_Handler(void) {
  for (;;) {
  }
}

__attribute__((section(".isr_vector"), used)) void (*const g_vectors[16])(void) = {
    (void (*)(void))(&_estack), Reset_Handler, Default_Handler, Default_Handler, Default_Handler,
    Default_Handler, Default_Handler, 0, 0, 0, 0, Default_Handler, Default_Handler, 0, Default_Handler,
    SysTick_Handler,
};

/* What crti/crtbegin would provide without -nostartfiles: static destructors are registered against
 * __dso_handle (never run: main() does not return); _init/_fini are empty on this target. */
void* __dso_handle = 0;
void _init(void) {}
void _fini(void) {}
