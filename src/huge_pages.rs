//! The process's allocator: the system's, with large blocks advised onto transparent huge pages.
//!
//! A run holds a few large blocks (a data set's decoded images: 768 MB for lego's 100 views at 800²; the
//! params' training state) that are written once, page by page. Where the kernel makes transparent huge
//! pages on request only (`madvise`, the default of most distributions), each 4 KiB page of them is a
//! page fault; on a virtual machine measured 2026-12-03 those faults took most of the time of loading
//! lego at 800² (9–11 s, against 1.8–2.5 s with huge pages). Blocks of [`LARGE`] bytes or more are
//! therefore advised (`MADV_HUGEPAGE`) over the 2 MiB pages they hold whole, before anything is written
//! to them. Smaller blocks, and every other system, are the system allocator's alone.

use std::alloc::{GlobalAlloc, Layout, System};

/// Blocks of at least this many bytes are advised onto huge pages.
const LARGE: usize = 4 << 20;

/// The size of a transparent huge page on x86-64 and aarch64 Linux.
#[cfg(target_os = "linux")]
const HUGE_PAGE: usize = 2 << 20;

/// The system allocator, with blocks of [`LARGE`] bytes or more on transparent huge pages where the
/// kernel has them.
pub struct HugePages;

// SAFETY: every call is passed to the system allocator with its own arguments; the advice changes how the
// kernel backs pages of a block the system allocator returned, not what the block holds or where it is.
unsafe impl GlobalAlloc for HugePages {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's guarantees are passed on.
        let block = unsafe { System.alloc(layout) };
        advise(block, layout.size());
        block
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: as for `alloc`.
        let block = unsafe { System.alloc_zeroed(layout) };
        advise(block, layout.size());
        block
    }

    unsafe fn dealloc(&self, block: *mut u8, layout: Layout) {
        // SAFETY: as for `alloc`.
        unsafe { System.dealloc(block, layout) }
    }

    unsafe fn realloc(&self, block: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: as for `alloc`.
        let moved = unsafe { System.realloc(block, layout, new_size) };
        advise(moved, new_size);
        moved
    }
}

/// Advises the kernel to back the whole huge pages of the `size` bytes at `block` with huge pages, when
/// the block is [`LARGE`]. Advice the kernel refuses (no transparent huge pages) changes nothing.
fn advise(block: *mut u8, size: usize) {
    if block.is_null() || size < LARGE {
        return;
    }
    #[cfg(target_os = "linux")]
    {
        let start = (block as usize).next_multiple_of(HUGE_PAGE);
        let end = (block as usize + size) / HUGE_PAGE * HUGE_PAGE;
        if end > start {
            // SAFETY: the range lies inside a block the system allocator returned (whole pages of it, the
            // 2 MiB boundaries being page boundaries); MADV_HUGEPAGE leaves its contents as they are.
            unsafe { libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_HUGEPAGE) };
        }
    }
}
