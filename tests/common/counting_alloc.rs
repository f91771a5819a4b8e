//! A counting global allocator for the zero-allocation tests: it forwards to the system
//! allocator and, while counting is switched on for the current thread, counts every
//! allocation and reallocation made on that thread (deallocations are free). A test file
//! installs it with
//!
//! ```ignore
//! mod common;
//! #[global_allocator]
//! static GLOBAL: common::counting_alloc::Counting = common::counting_alloc::Counting;
//! ```
#![allow(dead_code)] // each test file uses part of the helper

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

/// The allocator; install it with `#[global_allocator]` in the test file.
pub struct Counting;

thread_local! {
    static COUNTING: Cell<bool> = const { Cell::new(false) };
    static ALLOCS: Cell<usize> = const { Cell::new(0) };
}

fn note() {
    // try_with: the allocator may run while this thread's locals are being torn down
    let on = COUNTING.try_with(|c| c.get()).unwrap_or(false);
    if on {
        let _ = ALLOCS.try_with(|a| a.set(a.get() + 1));
    }
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note();
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note();
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note();
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

/// Reset this thread's count and start counting.
pub fn start() {
    ALLOCS.with(|a| a.set(0));
    COUNTING.with(|c| c.set(true));
}

/// Stop counting on this thread and return the number of allocations since [`start`].
pub fn stop() -> usize {
    COUNTING.with(|c| c.set(false));
    ALLOCS.with(|a| a.get())
}

/// Run `f` and return the number of allocations it made on this thread.
pub fn count_allocs<R>(f: impl FnOnce() -> R) -> (R, usize) {
    start();
    let r = f();
    (r, stop())
}
