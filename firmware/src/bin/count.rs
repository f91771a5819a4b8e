//! Instruction counts of the core's per-sample and per-solve work on the Cortex-M4F
//! (issue 18), for `scripts/count-instructions.sh`: QEMU runs this image with
//! `-icount shift=0` (every guest instruction advances the virtual clock by exactly 1 ns), the
//! SysTick counts that clock, and a calibration loop of a known number of instructions gives
//! the instructions per SysTick tick (40 at the board's 25 MHz). Each measurement runs the
//! same code the device firmware links (`lpvid` with f32, release profile: `opt-level = "s"`,
//! LTO) on statistics in static storage and prints one line on UART0; the image then exits
//! through semihosting.
//!
//! These are instructions, not cycles: on a real Cortex-M4F a load takes 2 cycles, a
//! floating multiply-add 3, a division or square root 14, so cycles are somewhat more.
#![no_std]
#![no_main]

use core::fmt::Write;
use core::ptr::{addr_of_mut, read_volatile, write_volatile};

use cortex_m_rt::entry;
use lpvid::device::{solve_statistics, solver_len};
use lpvid::protocol::SolveRequest;
use lpvid::sliding::rebase_gram;
use lpvid::stats::stat_vector_len_const;
use lpvid::{packed_len, window_storage_len, Gram, PbsidDims, PbsidStats, StatsLayout, Summation};
use panic_halt as _;

/// Largest statistic vector measured: r = l = s = 1, p = 4, extended (126).
const LMAX: usize = stat_vector_len_const(1, 1, 1, 4, true);
/// Three packed triangles: compensated sums plus a window's snapshot.
const GMAX: usize = 3 * packed_len(LMAX);
const SOLVER: usize = solver_len(1, 61, true);

static mut GRAM: [f32; GMAX] = [0.0; GMAX];
static mut WINDOW: [f32; 64] = [0.0; 64];
static mut VECTOR: [f32; LMAX] = [0.0; LMAX];
static mut SOLVER_BUF: [f32; SOLVER] = [0.0; SOLVER];

const SYST_CSR: *mut u32 = 0xE000_E010 as *mut u32;
const SYST_RVR: *mut u32 = 0xE000_E014 as *mut u32;
const SYST_CVR: *mut u32 = 0xE000_E018 as *mut u32;

fn systick_start() {
    // SAFETY: the SysTick registers of the Cortex-M4.
    unsafe {
        write_volatile(SYST_RVR, 0x00FF_FFFF);
        write_volatile(SYST_CVR, 0);
        // enable, no interrupt, processor clock
        write_volatile(SYST_CSR, 0b101);
    }
}

/// SysTick ticks taken by `f`, or `None` if the 24-bit counter wrapped (COUNTFLAG) and the
/// count is ambiguous.
fn ticks_of(f: impl FnOnce()) -> Option<u32> {
    // SAFETY: as in `systick_start`; reading CSR clears COUNTFLAG.
    let c0 = unsafe {
        let _ = read_volatile(SYST_CSR);
        read_volatile(SYST_CVR)
    };
    f();
    // SAFETY: as above.
    let (c1, csr) = unsafe { (read_volatile(SYST_CVR), read_volatile(SYST_CSR)) };
    if csr & (1 << 16) != 0 && c1 <= c0 {
        // wrapped: at least one full period passed
        return None;
    }
    Some(c0.wrapping_sub(c1) & 0x00FF_FFFF)
}

/// UART0 (CMSDK APB UART) of the mps2-an386, transmit only.
struct Uart;

impl Uart {
    fn init(&self) {
        // SAFETY: the UART0 registers of this board.
        unsafe {
            write_volatile((0x4000_4000 + 0x10) as *mut u32, 16);
            write_volatile((0x4000_4000 + 0x08) as *mut u32, 1);
        }
    }
}

impl Write for Uart {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        for b in s.bytes() {
            // SAFETY: as in `init`; STATE bit 0 is "transmit buffer full".
            unsafe {
                while read_volatile((0x4000_4000 + 0x04) as *const u32) & 1 != 0 {}
                write_volatile(0x4000_4000 as *mut u32, b as u32);
            }
        }
        Ok(())
    }
}

/// Exit QEMU (semihosting SYS_EXIT, ADP_Stopped_ApplicationExit).
fn exit() -> ! {
    loop {
        // SAFETY: the semihosting call; QEMU runs with -semihosting-config enable=on.
        unsafe {
            core::arch::asm!("bkpt 0xab", in("r0") 0x18u32, in("r1") 0x20026u32);
        }
    }
}

/// Run `n` iterations of a 2-instruction loop (subs, bne): the calibration.
#[inline(never)]
fn spin(n: u32) {
    // SAFETY: register-only loop.
    unsafe {
        core::arch::asm!("2:", "subs {0}, {0}, #1", "bne 2b", inout(reg) n => _, options(nomem, nostack));
    }
}

/// xorshift in [-0.5, 0.5).
struct Rng(u32);
impl Rng {
    fn next(&mut self) -> f32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 17;
        self.0 ^= self.0 << 5;
        (self.0 >> 8) as f32 / (1u32 << 24) as f32 - 0.5
    }
}

/// A noise-free LPV-ARX plant (as the device tests'): sample k as [u, y, p].
struct Plant {
    rng: Rng,
    y1: f32,
    u1: f32,
    u2: f32,
    p1: f32,
    /// (cos, sin) of the scheduling's phase, rotated by 0.003 rad per sample
    cs: (f32, f32),
}

impl Plant {
    fn new() -> Self {
        Plant {
            rng: Rng(0x2545_f491),
            y1: 0.0,
            u1: 0.0,
            u2: 0.0,
            p1: 0.0,
            cs: (1.0, 0.0),
        }
    }
    fn next(&mut self) -> [f32; 3] {
        let u = 2.0 * self.rng.next();
        let p = self.cs.1;
        let (c, s) = self.cs;
        self.cs = (c * 0.999_995_5 - s * 0.003, s * 0.999_995_5 + c * 0.003);
        let y = (0.5 + 0.3 * self.p1) * self.y1 + self.u1 - 0.2 * self.u2 + 0.01 * self.rng.next();
        (self.y1, self.u2, self.u1, self.p1) = (y, self.u1, u, p);
        [u, y, p]
    }
}

/// Instructions per SysTick tick (calibrated).
struct Clock {
    per_tick: f32,
}

impl Clock {
    fn calibrate(out: &mut Uart) -> Self {
        // the counter reloads from 0 on its first tick: let it start
        spin(100);
        let n = 1_000_000u32;
        let t = ticks_of(|| spin(n)).unwrap_or(u32::MAX);
        let per_tick = (2 * n) as f32 / t as f32;
        let _ = writeln!(
            out,
            "calibration: {} instructions (subs/bne loop) in {t} SysTick ticks: {per_tick:.3} instructions per tick",
            2 * n
        );
        Clock { per_tick }
    }

    /// Instructions of `f`, run `reps` times, per run (NaN if the counter wrapped).
    fn per_run(&self, reps: u32, mut f: impl FnMut()) -> f32 {
        match ticks_of(|| {
            for _ in 0..reps {
                f();
            }
        }) {
            Some(t) => t as f32 * self.per_tick / reps as f32,
            None => f32::NAN,
        }
    }
}

/// Gram::update on vectors of length `len`: instructions per vector.
fn gram_update(clock: &Clock, len: usize, summation: Summation, lambda: f32) -> f32 {
    // SAFETY: single-threaded; the statics are used by one measurement at a time.
    let (g, v) = unsafe { (&mut *addr_of_mut!(GRAM), &mut *addr_of_mut!(VECTOR)) };
    let need = match summation {
        Summation::Plain => packed_len(len),
        Summation::Compensated => 2 * packed_len(len),
    };
    let mut gram = Gram::with_summation(len, &mut g[..need], summation).unwrap();
    gram.set_forgetting(lambda).unwrap();
    let mut rng = Rng(7);
    let vec = &mut v[..len];
    for x in vec.iter_mut() {
        *x = rng.next();
    }
    // warm up (and nothing exceptional: same vector each time, as a stream of equal cost)
    for _ in 0..4 {
        gram.update(vec).unwrap();
    }
    clock.per_run(64, || {
        vec[0] = -vec[0];
        gram.update(vec).unwrap();
    })
}

#[entry]
fn main() -> ! {
    let mut out = Uart;
    out.init();
    systick_start();
    let clock = Clock::calibrate(&mut out);
    let _ = writeln!(
        out,
        "# f32, lpvid core as linked by the firmware (opt-level s, LTO)"
    );

    // 1. Gram::update per vector: plain, compensated, compensated with forgetting
    for p in 2..=4usize {
        let len = stat_vector_len_const(1, 1, 1, p, true);
        let e = packed_len(len);
        let plain = gram_update(&clock, len, Summation::Plain, 1.0);
        let comp = gram_update(&clock, len, Summation::Compensated, 1.0);
        let forget = gram_update(&clock, len, Summation::Compensated, 0.995);
        let _ = writeln!(
            out,
            "gram_update p={p} dim={len} entries={e}: plain {plain:.0} ({:.2}/entry), compensated {comp:.0} ({:.2}/entry), compensated+forgetting {forget:.0} ({:.2}/entry)",
            plain / e as f32,
            comp / e as f32,
            forget / e as f32
        );
    }

    // 2. the device's per-sample work: PbsidStats::update (window, statistic vector, Gram)
    //    for r = l = s = 1, p = 3, extended, compensated; then the solves on those statistics
    let p = 3usize;
    let dims = PbsidDims::new(1, 1, 1, p).unwrap();
    let len = stat_vector_len_const(1, 1, 1, p, true);
    // SAFETY: as in `gram_update`.
    let (g, w, v, solver) = unsafe {
        (
            &mut *addr_of_mut!(GRAM),
            &mut *addr_of_mut!(WINDOW),
            &mut *addr_of_mut!(VECTOR),
            &mut *addr_of_mut!(SOLVER_BUF),
        )
    };
    let mut st = PbsidStats::with_storage(
        dims,
        StatsLayout::Extended,
        &mut w[..window_storage_len(1, 1, 1, p)],
        &mut g[..2 * packed_len(len)],
        &mut v[..len],
    )
    .unwrap();
    let mut plant = Plant::new();
    for _ in 0..200 {
        let s = plant.next();
        st.update(&s[..1], &s[1..2], &s[2..]).unwrap();
    }
    let per_sample = clock.per_run(500, || {
        let s = plant.next();
        st.update(&s[..1], &s[1..2], &s[2..]).unwrap();
    });
    // the plant's own cost (rng, rotation), measured alone and subtracted
    let mut plant2 = Plant::new();
    let mut sink = 0.0f32;
    let plant_cost = clock.per_run(500, || {
        let s = plant2.next();
        sink += s[1];
    });
    let _ = writeln!(
        out,
        "stats_update p={p} dim={len} entries={}: {:.0} per sample (PbsidStats::update, compensated; plant generator {plant_cost:.0} subtracted) [{sink:.1}]",
        packed_len(len),
        per_sample - plant_cost
    );

    // 3. solves of problem (13) on the statistics of 700 samples (q + r = 29 columns, l = 1)
    for (ratio, name) in [(0.0f32, "least squares"), (0.01, "lasso 0.01 lambda_max")] {
        let req = SolveRequest {
            lambda_ratio: ratio,
            group: false,
            standardise: true,
        };
        let mut iters = 0;
        let cold = clock.per_run(1, || {
            solver.fill(0.0);
            iters = solve_statistics(st.gram(), &dims, &req, solver, false)
                .map(|s| s.iterations)
                .unwrap_or(0);
        });
        // the recursive estimate: 100 more samples, then a warm-started solve
        for _ in 0..100 {
            let s = plant.next();
            st.update(&s[..1], &s[1..2], &s[2..]).unwrap();
        }
        let mut witers = 0;
        let warm = clock.per_run(1, || {
            witers = solve_statistics(st.gram(), &dims, &req, solver, true)
                .map(|s| s.iterations)
                .unwrap_or(0);
        });
        let _ = writeln!(
            out,
            "solve p={p} columns={} ({name}): cold {cold:.0} ({iters} iterations), warm after 100 samples {warm:.0} ({witers} iterations)",
            lpvid::regressor_len(1, 1, 1, p).unwrap_or(0) + 1
        );
    }

    // 4. a sliding window's rebase (once per N/2 vectors), plain triangle with its snapshot
    {
        let len = stat_vector_len_const(1, 1, 1, 3, true);
        let n = packed_len(len);
        let mut gram = Gram::with_summation(len, &mut g[..3 * n], Summation::Compensated).unwrap();
        let vec = &mut v[..len];
        gram.update(vec).unwrap();
        let reb = clock.per_run(16, || {
            rebase_gram(&mut gram, None, 1).unwrap();
        });
        let _ = writeln!(
            out,
            "rebase dim={len} entries={n}: {reb:.0} per rebase ({:.2}/entry), compensated",
            reb / n as f32
        );
    }
    let _ = writeln!(out, "done");
    exit()
}
