//! Large tables on 2 MiB pages where the system allows them.
//!
//! A render reads the hierarchy's nodes and triangle blocks, the face
//! normals and the per-pixel materials at random: tens of megabytes that
//! on 4 KiB pages miss the TLB on most accesses. Linux backs memory
//! advised with `MADV_HUGEPAGE` by 2 MiB pages when transparent huge
//! pages are `always` or `madvise` (a common default). [`huge`] copies a
//! table into memory advised so before it is first touched. It changes
//! no value, only where the bytes live; elsewhere, or where the advice is
//! refused, the table is returned as it was.

/// Below this a table keeps its allocation: it would get no 2 MiB page.
const MIN_BYTES: usize = 4 << 20;

/// `v`, on memory advised to use 2 MiB pages when it is large enough and
/// the system supports the advice; the same elements in the same order.
pub fn huge<T: Copy>(v: Vec<T>) -> Vec<T> {
    let bytes = std::mem::size_of_val(v.as_slice());
    if bytes < MIN_BYTES {
        return v;
    }
    let mut out: Vec<T> = Vec::with_capacity(v.len());
    if !advise(out.as_mut_ptr() as *mut u8, bytes) {
        return v;
    }
    out.extend_from_slice(&v);
    out
}

/// Advises the 2 MiB-aligned part of `[ptr, ptr + len)`, not yet touched,
/// to be backed by huge pages; whether the advice was taken.
#[cfg(target_os = "linux")]
fn advise(ptr: *mut u8, len: usize) -> bool {
    const PAGE: usize = 2 << 20;
    let start = (ptr as usize).next_multiple_of(PAGE);
    let end = (ptr as usize + len) / PAGE * PAGE;
    if end <= start {
        return false;
    }
    // SAFETY: [start, end) lies inside the allocation of `len` bytes at
    // `ptr`, which is ours; MADV_HUGEPAGE changes no contents or access.
    unsafe { libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_HUGEPAGE) == 0 }
}

#[cfg(not(target_os = "linux"))]
fn advise(_ptr: *mut u8, _len: usize) -> bool {
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_table_keeps_its_elements_small_or_large() {
        let small: Vec<u32> = (0..1000).collect();
        assert_eq!(huge(small.clone()), small);
        let large: Vec<[f32; 3]> = (0..600_000).map(|i| [i as f32, -(i as f32), 0.5]).collect();
        assert!(std::mem::size_of_val(large.as_slice()) >= MIN_BYTES);
        assert_eq!(huge(large.clone()), large);
    }
}
