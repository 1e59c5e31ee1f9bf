//! The activation slots and the kernels' scratch, on transparent huge pages where the
//! system offers them.
//!
//! The conv kernels work in NCHW: a tile of pixels touches every channel's plane, each a
//! plane apart (12 KiB for a 56x56 plane), so one tile of a 64-channel layer reads and
//! writes at 64 to 128 pages. On 4 KiB pages that misses the first-level TLB on nearly
//! every row. A 2 MiB page covers 40 such planes. Linux backs anonymous memory with huge
//! pages only where the program asks (`madvise(MADV_HUGEPAGE)`, the default setting
//! `transparent_hugepage=madvise`), so a buffer of at least [`HUGE`] bytes is mapped
//! here with its start on a 2 MiB boundary and its whole 2 MiB extents advised; the
//! tail past the last whole extent stays on small pages, so a buffer takes no more
//! memory than its length. Smaller buffers, other systems, or a refused mapping fall
//! back to the heap.
//!
//! Measured on a 2-core Xeon (2026-12-05, alternating rounds, 1 / 2 threads, the
//! heap against this): ResNet-50 0.92 / 0.96 of the time, ResNet-18 0.96 / 0.93,
//! MobileNetV2 0.98 / 0.95 (in another run its 1x1 convs 0.90), EfficientNet-B0 1.01 /
//! 0.89; the transformers, whose linears read contiguous rows, 0.99-1.01.

use std::ops::{Deref, DerefMut};

/// A huge page's size, and the smallest buffer mapped on them.
const HUGE: usize = 2 << 20;

/// A zero-filled buffer of `f32`.
pub(crate) enum Buffer {
    Heap(Vec<f32>),
    /// `len` floats from byte `start` (a multiple of [`HUGE`] from the system's alignment
    /// of the mapping's address) of an anonymous mapping.
    Mapped {
        map: memmap2::MmapMut,
        start: usize,
        len: usize,
    },
}

impl Default for Buffer {
    fn default() -> Self {
        Buffer::Heap(Vec::new())
    }
}

impl Buffer {
    /// `n` zeros: on huge pages if the buffer is large enough and the system lets it.
    pub(crate) fn zeroed(n: usize) -> Buffer {
        Buffer::mapped(n).unwrap_or_else(|| Buffer::Heap(vec![0.0; n]))
    }

    /// Whether any of the buffer is advised onto huge pages.
    #[cfg(test)]
    pub(crate) fn is_mapped(&self) -> bool {
        matches!(self, Buffer::Mapped { .. })
    }

    #[cfg(target_os = "linux")]
    fn mapped(n: usize) -> Option<Buffer> {
        let bytes = n.checked_mul(size_of::<f32>())?;
        if bytes < HUGE {
            return None;
        }
        // One extent more than needed, to start on a boundary whatever address the system
        // gives; the pages of the unused ends are never touched, so never resident.
        let map = memmap2::MmapMut::map_anon(bytes.checked_add(HUGE)?).ok()?;
        let start = (HUGE - map.as_ptr() as usize % HUGE) % HUGE;
        // Advice is a hint: where the system refuses it the buffer still works.
        let _ = map.advise_range(memmap2::Advice::HugePage, start, bytes / HUGE * HUGE);
        Some(Buffer::Mapped { map, start, len: n })
    }

    #[cfg(not(target_os = "linux"))]
    fn mapped(_: usize) -> Option<Buffer> {
        None
    }
}

impl Deref for Buffer {
    type Target = [f32];
    fn deref(&self) -> &[f32] {
        match self {
            Buffer::Heap(v) => v,
            // Aligned to 4 bytes (a page-aligned mapping, `start` a multiple of `HUGE`).
            Buffer::Mapped { map, start, len } => bytemuck::cast_slice(&map[*start..][..len * size_of::<f32>()]),
        }
    }
}

impl DerefMut for Buffer {
    fn deref_mut(&mut self) -> &mut [f32] {
        match self {
            Buffer::Heap(v) => v,
            Buffer::Mapped { map, start, len } => {
                bytemuck::cast_slice_mut(&mut map[*start..][..*len * size_of::<f32>()])
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zeroed_on_either_side_of_the_bound_and_writable() {
        for n in [0, 1, HUGE / 4 - 1, HUGE / 4, HUGE / 4 + 5, 3 * HUGE / 4 + 7] {
            let mut b = Buffer::zeroed(n);
            assert_eq!(b.len(), n);
            assert!(b.iter().all(|&v| v == 0.0), "{n}: not zeroed");
            b.iter_mut().enumerate().for_each(|(i, v)| *v = i as f32);
            assert!(b.iter().enumerate().all(|(i, &v)| v == i as f32), "{n}: lost a write");
            if cfg!(target_os = "linux") {
                assert_eq!(b.is_mapped(), n * 4 >= HUGE, "{n}");
            }
            if let Buffer::Mapped { map, start, .. } = &b {
                assert_eq!((map.as_ptr() as usize + start) % HUGE, 0, "{n}: not on a boundary");
            }
        }
        assert!(Buffer::default().is_empty());
    }
}
