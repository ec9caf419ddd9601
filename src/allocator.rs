//! The heap allocator of vesselflow's programs (the command line and the Python
//! module declare it their `#[global_allocator]`; the library itself does not): the
//! system's, except that blocks of [`LARGE`] bytes or more are mapped from the
//! operating system on their own and unmapped when freed.
//!
//! Why: the run's large arrays (a graph's positions, the normal matrix, the
//! conjugate-gradient vectors) are freed and allocated again every contraction
//! iteration, from rayon's worker threads. glibc maps a large block on its own only
//! while the block is above its mmap threshold, and raises that threshold to the size
//! of every mapped block freed (up to 32 MiB); from then on blocks of that size come
//! from the worker threads' arenas, whose free tops `malloc_trim` does not return. On
//! `damseh_synth2` that kept 10–20 MB of freed pages resident at the contraction's
//! peak, which varied from run to run with the threads' timing (peak RSS over the mask
//! 150–172 bytes per vessel voxel in repeated runs; 143–144 with every large block
//! mapped, as glibc does with a fixed `M_MMAP_THRESHOLD`). The wall time did not
//! change measurably (256³ and 512³ beds). A library cannot fix the threshold for its
//! host process; a global allocator of the program touches only its own blocks.
//!
//! Mapped memory reads as zero, so a large zeroed block costs no writes; a large block
//! that grows or shrinks is moved by `mremap` on Linux (no copy), elsewhere by a copy.
//! Off Unix, and for blocks aligned beyond a page, the system allocator serves all.

use std::alloc::{GlobalAlloc, Layout, System};

/// Blocks of at least this many bytes are mapped on their own.
pub const LARGE: usize = 1 << 20;

/// The allocator (module doc). Declare it with
/// `#[global_allocator] static ALLOCATOR: vesselflow::allocator::Allocator = vesselflow::allocator::Allocator;`.
#[derive(Debug, Default, Clone, Copy)]
pub struct Allocator;

/// Alignment every mapping has (the smallest page size of the supported systems).
const PAGE: usize = 4096;

/// Whether a block of this layout is mapped on its own. `dealloc` and `realloc` get
/// the layout the block was allocated with, so they decide the same way.
fn mapped(layout: Layout) -> bool {
    cfg!(unix) && layout.size() >= LARGE && layout.align() <= PAGE
}

#[cfg(unix)]
mod os {
    /// `size` bytes of fresh zero pages, or null.
    pub unsafe fn map(size: usize) -> *mut u8 {
        // SAFETY: an anonymous private mapping at an address of the kernel's choice
        // touches no existing memory.
        let p = unsafe {
            libc::mmap(
                std::ptr::null_mut(),
                size,
                libc::PROT_READ | libc::PROT_WRITE,
                libc::MAP_PRIVATE | libc::MAP_ANONYMOUS,
                -1,
                0,
            )
        };
        if p == libc::MAP_FAILED {
            std::ptr::null_mut()
        } else {
            p.cast()
        }
    }

    /// Unmap a block of `size` bytes that [`map`] or [`remap`] returned.
    pub unsafe fn unmap(ptr: *mut u8, size: usize) {
        // SAFETY: the caller passes a mapping of this length; a failure (which only an
        // invalid argument could cause) leaks it rather than corrupting memory.
        unsafe {
            libc::munmap(ptr.cast(), size);
        }
    }

    /// The block `ptr` of `old` bytes resized to `new` bytes (moved if need be), its
    /// contents kept up to the shorter length; null (the block left as it was) if the
    /// system refuses.
    #[cfg(target_os = "linux")]
    pub unsafe fn remap(ptr: *mut u8, old: usize, new: usize) -> *mut u8 {
        // SAFETY: `ptr` is a mapping of `old` bytes; MREMAP_MAYMOVE lets the kernel pick
        // the new address, and on failure the old mapping is untouched.
        let p = unsafe { libc::mremap(ptr.cast(), old, new, libc::MREMAP_MAYMOVE) };
        if p == libc::MAP_FAILED {
            std::ptr::null_mut()
        } else {
            p.cast()
        }
    }
}

#[cfg(not(unix))]
mod os {
    pub unsafe fn map(_: usize) -> *mut u8 {
        unreachable!("blocks are mapped on Unix only")
    }
    pub unsafe fn unmap(_: *mut u8, _: usize) {
        unreachable!("blocks are mapped on Unix only")
    }
}

// SAFETY: every block is either the system allocator's (small or over-aligned
// layouts, decided by `mapped` from the layout alone) or a private mapping of at least
// its size, page-aligned (so aligned for every layout `mapped` accepts), and each is
// freed or resized by the side that made it.
unsafe impl GlobalAlloc for Allocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if mapped(layout) {
            unsafe { os::map(layout.size()) }
        } else {
            unsafe { System.alloc(layout) }
        }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if mapped(layout) {
            // Fresh mappings are zero.
            unsafe { os::map(layout.size()) }
        } else {
            unsafe { System.alloc_zeroed(layout) }
        }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        if mapped(layout) {
            unsafe { os::unmap(ptr, layout.size()) }
        } else {
            unsafe { System.dealloc(ptr, layout) }
        }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: the caller guarantees that `new_size`, rounded up to the alignment,
        // does not overflow `isize`.
        let new = unsafe { Layout::from_size_align_unchecked(new_size, layout.align()) };
        match (mapped(layout), mapped(new)) {
            (false, false) => unsafe { System.realloc(ptr, layout, new_size) },
            #[cfg(target_os = "linux")]
            (true, true) => unsafe { os::remap(ptr, layout.size(), new_size) },
            _ => {
                let p = unsafe { self.alloc(new) };
                if !p.is_null() {
                    unsafe {
                        std::ptr::copy_nonoverlapping(ptr, p, layout.size().min(new_size));
                        self.dealloc(ptr, layout);
                    }
                }
                p
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Blocks on both sides of [`LARGE`], grown and shrunk across it and within each
    /// side, keep their contents; zeroed blocks read zero, also after a block of the
    /// same size was freed dirty.
    #[test]
    fn blocks_keep_their_contents_across_the_threshold() {
        let a = Allocator;
        let fill = |p: *mut u8, n: usize| (0..n).for_each(|i| unsafe { *p.add(i) = (i % 251) as u8 });
        let check = |p: *const u8, n: usize| (0..n).all(|i| unsafe { *p.add(i) } == (i % 251) as u8);
        let steps = [1000, LARGE - 8, LARGE, 3 * LARGE + 5, LARGE + 1, 64, 5 * LARGE];
        let mut layout = Layout::from_size_align(steps[0], 8).unwrap();
        let mut p = unsafe { a.alloc(layout) };
        assert!(!p.is_null());
        fill(p, layout.size());
        for &size in &steps[1..] {
            let keep = layout.size().min(size);
            p = unsafe { a.realloc(p, layout, size) };
            assert!(!p.is_null(), "realloc to {size}");
            assert!(check(p, keep), "contents lost growing or shrinking to {size}");
            layout = Layout::from_size_align(size, 8).unwrap();
            fill(p, size);
        }
        unsafe { a.dealloc(p, layout) };
        for size in [100, 2 * LARGE] {
            let layout = Layout::from_size_align(size, 16).unwrap();
            let dirty = unsafe { a.alloc(layout) };
            fill(dirty, size);
            unsafe { a.dealloc(dirty, layout) };
            let z = unsafe { a.alloc_zeroed(layout) };
            assert!((0..size).all(|i| unsafe { *z.add(i) } == 0), "zeroed block of {size}");
            assert_eq!(z as usize % 16, 0);
            unsafe { a.dealloc(z, layout) };
        }
    }

    /// Large blocks are page-aligned mappings; over-aligned and small ones are the
    /// system's.
    #[test]
    fn only_large_blocks_of_page_alignment_are_mapped() {
        assert!(mapped(Layout::from_size_align(LARGE, 64).unwrap()) == cfg!(unix));
        assert!(!mapped(Layout::from_size_align(LARGE - 1, 8).unwrap()));
        assert!(!mapped(Layout::from_size_align(LARGE, 2 * PAGE).unwrap()));
        let a = Allocator;
        let layout = Layout::from_size_align(LARGE, PAGE).unwrap();
        let p = unsafe { a.alloc(layout) };
        assert_eq!(p as usize % PAGE, 0);
        unsafe { a.dealloc(p, layout) };
    }
}
