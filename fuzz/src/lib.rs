//! What every fuzz target links: an allocator that aborts on any single allocation
//! over [`LIMIT`], so that a reader reserving memory from a hostile length field is a
//! crash the fuzzer saves, touched or not.
//!
//! libFuzzer's own `-malloc_limit_mb` works through a sanitizer's malloc hooks, and
//! the targets are built without a sanitizer (`--sanitizer none`, docs/fuzzing.md):
//! there it checks nothing, and `-rss_limit_mb` sees only memory that is written. A
//! `Vec::with_capacity(4 << 30)` never filled passed both.
//!
//! This crate is outside the workspace and its `unsafe` ban: implementing
//! `GlobalAlloc` is `unsafe` by definition, and each block below only forwards to the
//! system allocator.
use std::alloc::{GlobalAlloc, Layout, System};

/// Largest single allocation, bytes: the 2 GiB the fuzz runs give `-rss_limit_mb`.
pub const LIMIT: usize = 2 << 30;

/// The system allocator, refusing allocations over [`LIMIT`] with an abort.
pub struct Limited;

#[global_allocator]
static ALLOCATOR: Limited = Limited;

/// Says what was asked for and aborts (an allocator must not unwind); libFuzzer
/// reports the abort as a deadly signal and keeps the input.
#[cold]
fn refuse(size: usize) -> ! {
    use std::io::Write;
    // A fixed buffer: formatting into it allocates nothing.
    let mut line = [0u8; 128];
    let mut cursor = std::io::Cursor::new(&mut line[..]);
    let _ = writeln!(
        cursor,
        "==ERROR: an allocation of {size} bytes, over the fuzz limit of {LIMIT}"
    );
    let end = cursor.position() as usize;
    let _ = std::io::stderr().write_all(&line[..end]);
    std::process::abort()
}

// SAFETY: every method checks the size and then forwards its arguments unchanged to
// `System`, so the caller's obligations to this allocator are exactly its obligations
// to `System`, which upholds `GlobalAlloc`'s contract.
unsafe impl GlobalAlloc for Limited {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if layout.size() > LIMIT {
            refuse(layout.size());
        }
        // SAFETY: as above; `layout` is the caller's, non-zero-sized by contract.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if layout.size() > LIMIT {
            refuse(layout.size());
        }
        // SAFETY: as above.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if new_size > LIMIT {
            refuse(new_size);
        }
        // SAFETY: `ptr` was allocated by `System` through this allocator with `layout`.
        unsafe { System.realloc(ptr, layout, new_size) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` was allocated by `System` through this allocator with `layout`.
        unsafe { System.dealloc(ptr, layout) }
    }
}
