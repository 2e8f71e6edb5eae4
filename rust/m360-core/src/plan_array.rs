//! The arrays of plan maps: built in memory, or read in place from a memory-mapped plan file.
//!
//! A map loaded from the disk cache ([`crate::plan_cache`]) keeps the file mapped and reads its
//! arrays there: no copy, no fresh pages to fault in and zero, and processes that load the same
//! plan share its pages in the page cache. The loader checks every such array (length,
//! alignment, every index the kernels follow) before it hands one out, exactly as it checked
//! the copies before.

use memmap2::Mmap;
use std::marker::PhantomData;
use std::ops::{Deref, Range};
use std::sync::Arc;

/// An array of a plan map: owned, or a slice of a mapped plan file that lives as long as the
/// array does.
#[derive(Debug, Clone)]
pub(crate) enum PlanArray<T> {
    /// Built (or copied) in memory.
    Owned(Vec<T>),
    /// `bytes` of `file`, whose length is a whole number of `T` and whose start is aligned for
    /// `T` (checked by [`PlanArray::mapped`]).
    Mapped {
        file: Arc<Mmap>,
        bytes: Range<usize>,
        element: PhantomData<T>,
    },
}

impl<T: bytemuck::Pod> PlanArray<T> {
    /// `bytes` of `file` as an array of `T`, or `None` if they are out of the file, not a
    /// whole number of `T` or not aligned for `T`.
    pub(crate) fn mapped(file: &Arc<Mmap>, bytes: Range<usize>) -> Option<Self> {
        bytemuck::try_cast_slice::<u8, T>(file.get(bytes.clone())?).ok()?;
        Some(Self::Mapped {
            file: file.clone(),
            bytes,
            element: PhantomData,
        })
    }

    /// Whether the array is read in place from a mapped file.
    pub(crate) fn is_mapped(&self) -> bool {
        matches!(self, Self::Mapped { .. })
    }
}

impl<T> Default for PlanArray<T> {
    fn default() -> Self {
        Self::Owned(Vec::new())
    }
}

impl<T> From<Vec<T>> for PlanArray<T> {
    fn from(v: Vec<T>) -> Self {
        Self::Owned(v)
    }
}

impl<T: bytemuck::Pod> Deref for PlanArray<T> {
    type Target = [T];

    #[inline]
    fn deref(&self) -> &[T] {
        match self {
            Self::Owned(v) => v,
            // Checked when made (in range, whole, aligned), so this never takes the empty
            // fallback; it exists so that no path can panic.
            Self::Mapped { file, bytes, .. } => file
                .get(bytes.clone())
                .and_then(|b| bytemuck::try_cast_slice(b).ok())
                .unwrap_or_default(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use memmap2::MmapOptions;

    fn file_of(bytes: &[u8]) -> Arc<Mmap> {
        let path = std::env::temp_dir().join(format!("m360-plan-array-{}", std::process::id()));
        std::fs::write(&path, bytes).expect("write");
        let file = std::fs::File::open(&path).expect("open");
        // SAFETY: the test's own file, not modified while mapped.
        let map = unsafe { MmapOptions::new().map(&file) }.expect("map");
        drop(std::fs::remove_file(&path));
        Arc::new(map)
    }

    #[test]
    fn mapped_arrays_read_the_file_in_place_and_refuse_bad_ranges() {
        let words: Vec<u32> = (0..64).collect();
        let file = file_of(bytemuck::cast_slice(&words));
        let all = PlanArray::<u32>::mapped(&file, 0..256).expect("whole file");
        assert_eq!(&*all, words.as_slice());
        assert!(all.is_mapped());
        let part = PlanArray::<u32>::mapped(&file, 8..24).expect("part");
        assert_eq!(&*part, &words[2..6]);
        assert!(
            PlanArray::<u32>::mapped(&file, 0..257).is_none(),
            "past the end"
        );
        assert!(PlanArray::<u32>::mapped(&file, 0..6).is_none(), "not whole");
        assert!(
            PlanArray::<u32>::mapped(&file, 2..10).is_none(),
            "misaligned"
        );
        let owned = PlanArray::from(words.clone());
        assert_eq!(&*owned, words.as_slice());
        assert!(!owned.is_mapped());
    }
}
