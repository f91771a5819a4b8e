//! lpvid firmware: the core's device engine ([`lpvid::device`]) with f32 statistics in
//! static storage, served on UART0 of the QEMU `mps2-an386` board (Cortex-M4F, ARM CMSDK
//! APB UART at 0x4000_4000).
//!
//! The main loop polls the UART: bytes that arrived are handed to the engine, whose reply
//! frames are written back byte by byte. While the engine works on a frame the host is
//! waiting for its reply (stop-and-wait), so the one-byte receive register loses nothing;
//! on real hardware with a streaming host an interrupt-driven receive ring would be the
//! next step.
//!
//! Capacities ([`lpvid::device::sizes`]): r = l = s = 1 up to p = 4 with the extended
//! layout (8 001 Gram values, stored twice: compensated sums), any configuration whose statistics fit as much (e.g.
//! r = 2, l = 3, s = 3, p = 1), on-device solves up to 61 columns, models up to n = 8.
//!
//! Memory: the engine lives in the static `ENGINE` (.bss); a configuration builds the
//! statistics inside it in place (`PbsidStatsArrays::init_in_place`), so the stack never holds
//! a copy of the Gram: `make device-test` measures a 3.7 KiB stack high-water mark.
#![no_std]
#![no_main]

use core::mem::MaybeUninit;
use core::ptr::{addr_of_mut, read_volatile, write_volatile};

use cortex_m_rt::entry;
use lpvid::device::DefaultDevice;
use panic_halt as _;

/// The device engine: f32 statistics, default capacities.
type Engine = DefaultDevice<f32>;

/// Static storage of the engine (in .bss: initialised at boot, not stored in flash).
static mut ENGINE: MaybeUninit<Engine> = MaybeUninit::uninit();

/// A minimal volatile-register driver of the ARM CMSDK APB UART.
struct Uart {
    base: usize,
}

impl Uart {
    const DATA: usize = 0x00;
    const STATE: usize = 0x04;
    const CTRL: usize = 0x08;
    const BAUDDIV: usize = 0x10;
    /// STATE: transmit buffer full.
    const TX_FULL: u32 = 1;
    /// STATE: receive buffer full.
    const RX_FULL: u32 = 2;
    /// CTRL: transmit enable | receive enable.
    const TX_RX_EN: u32 = 0b11;

    /// UART0 of the mps2-an386.
    const fn uart0() -> Self {
        Uart { base: 0x4000_4000 }
    }

    fn reg(&self, off: usize) -> *mut u32 {
        (self.base + off) as *mut u32
    }

    fn init(&self) {
        // SAFETY: the CMSDK UART registers of this board, 32-bit aligned.
        unsafe {
            write_volatile(self.reg(Self::BAUDDIV), 16);
            write_volatile(self.reg(Self::CTRL), Self::TX_RX_EN);
        }
    }

    fn try_read(&self) -> Option<u8> {
        // SAFETY: as in `init`.
        unsafe {
            if read_volatile(self.reg(Self::STATE)) & Self::RX_FULL != 0 {
                Some(read_volatile(self.reg(Self::DATA)) as u8)
            } else {
                None
            }
        }
    }

    fn write_all(&self, bytes: &[u8]) {
        for &b in bytes {
            // SAFETY: as in `init`.
            unsafe {
                while read_volatile(self.reg(Self::STATE)) & Self::TX_FULL != 0 {}
                write_volatile(self.reg(Self::DATA), b as u32);
            }
        }
    }
}

/// Fill the free RAM between the end of .bss and just below the current stack pointer with
/// a pattern, so a RAM dump (QEMU monitor `pmemsave`, see scripts/device-test.sh) shows the
/// stack's high-water mark: the first pattern word below the top of RAM.
fn paint_stack() {
    extern "C" {
        static mut __ebss: u32;
    }
    let start = (addr_of_mut!(__ebss) as usize + 3) & !3;
    let end = cortex_m::register::msp::read() as usize - 256;
    let mut p = start;
    while p < end {
        // SAFETY: free RAM between the statics and the live stack frame, word aligned.
        unsafe { write_volatile(p as *mut u32, STACK_PAINT) };
        p += 4;
    }
}

/// The stack paint pattern.
const STACK_PAINT: u32 = 0xA5A5_A5A5;

#[entry]
fn main() -> ! {
    paint_stack();
    let uart = Uart::uart0();
    uart.init();
    // SAFETY: the only reference to ENGINE, taken once before the loop.
    let engine: &'static mut Engine = unsafe { (*addr_of_mut!(ENGINE)).write(Engine::new()) };
    let mut buf = [0u8; 64];
    loop {
        let mut n = 0;
        while n < buf.len() {
            match uart.try_read() {
                Some(b) => {
                    buf[n] = b;
                    n += 1;
                }
                None => break,
            }
        }
        if n > 0 {
            engine.handle(&buf[..n], |frame| uart.write_all(frame));
        }
    }
}
