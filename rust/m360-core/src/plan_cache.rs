//! Built plan maps kept on disk, so that a new process loads a plan instead of building it.
//!
//! One file per map (tangent taps, ERP taps, overlap samples of one option set) in a folder
//! the caller chooses (Python: `$M360_HOME/plans`). A file is named and headed by what it
//! depends on — the map's kind and options, a 128-bit hash of the layout (ERP size, every
//! camera, the face polygons), the file format and the build of this crate
//! (its version and a hash of its sources, so a changed builder never reads an older map) —
//! and is trusted only after every check passes:
//!
//! - the header: magic, format, build, kind, layout hash, options, its own checksum;
//! - the payload: its exact length and an XXH3 checksum;
//! - the contents: every length and every index the kernels follow (several read without
//!   bounds checks) is validated against the layout, so a crafted file with a valid checksum
//!   still cannot cause a panic or an out-of-bounds read.
//!
//! Any failure is reported (the plan logs it) and the map is rebuilt and rewritten. Files are
//! written to a temporary name in the same folder, synced, then renamed over the target: two
//! processes building the same map both succeed (the last rename wins, both files are
//! complete), and a reader never sees a partial file. m360 never modifies a file in place.
//!
//! Loading memory-maps the file and, after the checks, reads the maps' large arrays in place
//! (`PlanArray`): the mapping lives as long as the map, nothing is copied, and processes
//! loading the same plan share its pages. That relies on the file never changing while it is
//! mapped; m360 never writes a plan file in place, so only the file's owner could. A file that
//! anyone else could write (another owner, or writable by group or others) is therefore copied
//! into memory instead, as are all files on platforms other than Unix (where a mapped file
//! could not be replaced or deleted).
//!
//! Layout of a file: a [`HEADER_BYTES`] header, then the sections (arrays in the in-memory
//! form of their elements, little-endian on every platform m360 ships for), each padded to
//! 8 bytes, so every section starts 8-byte aligned in a mapping. Section lengths are in the
//! header; the checksum covers all after it.

use crate::align::Overlaps;
use crate::layout::Layout;
use crate::plan_array::PlanArray;
use crate::resample::{ErpTaps, Run, TangentTaps, Tap, OFFSET_MASK, RANK_SHIFT, WRAPPED};
use memmap2::{Mmap, MmapOptions};
use rayon::prelude::*;
use std::fs::{self, File};
use std::io::{self, BufWriter, Seek, SeekFrom, Write};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use xxhash_rust::xxh3::{xxh3_128, xxh3_64, Xxh3};

/// Version of the file layout; bumped whenever it changes.
pub const FORMAT_VERSION: u32 = 2;
/// The build of the core that writes and reads plan files: version + hash of its sources.
pub const BUILD_ID: &str = concat!(
    env!("CARGO_PKG_VERSION"),
    "+",
    env!("M360_CORE_SOURCE_HASH")
);
/// Extension of plan files (temporary files end in `.tmp` instead).
pub const FILE_SUFFIX: &str = ".m360plan";

const MAGIC: [u8; 8] = *b"M360PLAN";
/// Bytes of the fixed header.
pub const HEADER_BYTES: usize = 256;
const MAX_SECTIONS: usize = 16;
const SECTIONS_AT: usize = 104;
const HEADER_SUM_AT: usize = HEADER_BYTES - 8;

/// The kinds of map a plan keeps.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// [`TangentTaps`].
    TangentTaps = 1,
    /// [`ErpTaps`].
    ErpTaps = 2,
    // 3 was per-tap blending weights, which the blends no longer read (they sample the weight
    // maps, computed on use): files of that kind are only left by older builds.
    /// [`Overlaps`] (options: sample fraction and pole cap as bit patterns).
    Overlaps = 4,
}

impl Kind {
    fn name(self) -> &'static str {
        match self {
            Kind::TangentTaps => "tangent-taps",
            Kind::ErpTaps => "erp-taps",
            Kind::Overlaps => "overlaps",
        }
    }
}

/// A map that can be stored in a plan file.
pub(crate) trait StoredMap: Sized {
    const KIND: Kind;
    /// Write the sections, each started with [`SectionWriter::section`].
    fn write<W: Write>(&self, out: &mut SectionWriter<W>) -> io::Result<()>;
    /// The map from the sections of `file`, every length and index checked against `layout`
    /// (and, for weights, against the plan's ERP taps `erp`).
    fn decode(file: &PlanFile, layout: &Layout, erp: Option<&ErpTaps>) -> Result<Self, String>;
    /// Whether the map reads its file in place (memory-mapped) instead of a copy.
    fn is_mapped(&self) -> bool {
        false
    }
}

/// 128-bit hash of everything the maps of `layout` depend on.
#[must_use]
pub fn layout_hash(layout: &Layout) -> u128 {
    let mut words: Vec<u64> = vec![
        layout.erp_height as u64,
        layout.erp_width as u64,
        layout.cameras.len() as u64,
    ];
    for cam in &layout.cameras {
        words.extend(cam.rotation.iter().map(|v| v.to_bits()));
        words.extend([cam.fx, cam.fy, cam.cx, cam.cy].map(f64::to_bits));
        words.extend([cam.width as u64, cam.height as u64]);
    }
    words.push(layout.face_polygons.len() as u64);
    for polygon in &layout.face_polygons {
        words.push(polygon.len() as u64);
        words.extend(polygon.iter().flatten().map(|v| v.to_bits()));
    }
    xxh3_128(bytemuck::cast_slice(&words))
}

/// File name of a map of `kind` with `options` for a layout of hash `layout`.
#[must_use]
pub fn file_name(kind: Kind, layout: &Layout, layout_hash: u128, options: [u64; 2]) -> String {
    format!(
        "{}-{}x{}-{layout_hash:032x}-{:016x}{:016x}-v{FORMAT_VERSION}-{BUILD_ID}{FILE_SUFFIX}",
        kind.name(),
        layout.erp_width,
        layout.erp_height,
        options[0],
        options[1],
    )
}

/// What identifies a file's contents.
struct Header {
    kind: u32,
    layout: u128,
    options: [u64; 2],
    payload_len: u64,
    checksum: u64,
    sections: Vec<u64>,
}

fn build_id_bytes() -> [u8; 32] {
    let mut out = [0u8; 32];
    let id = BUILD_ID.as_bytes();
    let n = id.len().min(32);
    out[..n].copy_from_slice(&id[..n]);
    out
}

impl Header {
    fn encode(&self) -> [u8; HEADER_BYTES] {
        let mut h = [0u8; HEADER_BYTES];
        h[0..8].copy_from_slice(&MAGIC);
        h[8..12].copy_from_slice(&FORMAT_VERSION.to_le_bytes());
        h[12..16].copy_from_slice(&self.kind.to_le_bytes());
        h[16..48].copy_from_slice(&build_id_bytes());
        h[48..64].copy_from_slice(&self.layout.to_le_bytes());
        h[64..72].copy_from_slice(&self.options[0].to_le_bytes());
        h[72..80].copy_from_slice(&self.options[1].to_le_bytes());
        h[80..88].copy_from_slice(&self.payload_len.to_le_bytes());
        h[88..96].copy_from_slice(&self.checksum.to_le_bytes());
        h[96..100].copy_from_slice(&(self.sections.len() as u32).to_le_bytes());
        for (k, len) in self.sections.iter().enumerate() {
            let at = SECTIONS_AT + 8 * k;
            h[at..at + 8].copy_from_slice(&len.to_le_bytes());
        }
        let sum = xxh3_64(&h[..HEADER_SUM_AT]);
        h[HEADER_SUM_AT..].copy_from_slice(&sum.to_le_bytes());
        h
    }

    /// The header of `bytes` (at least [`HEADER_BYTES`] long), if it is an intact plan header
    /// of this format and build.
    fn decode(h: &[u8]) -> Result<Self, String> {
        let u32_at = |at: usize| u32::from_le_bytes(h[at..at + 4].try_into().unwrap_or_default());
        let u64_at = |at: usize| u64::from_le_bytes(h[at..at + 8].try_into().unwrap_or_default());
        if h[0..8] != MAGIC {
            return Err("not a plan file (no magic)".into());
        }
        if xxh3_64(&h[..HEADER_SUM_AT]) != u64_at(HEADER_SUM_AT) {
            return Err("header checksum mismatch".into());
        }
        let format = u32_at(8);
        if format != FORMAT_VERSION {
            return Err(format!(
                "file format {format}, this build reads {FORMAT_VERSION}"
            ));
        }
        if h[16..48] != build_id_bytes() {
            let theirs = String::from_utf8_lossy(&h[16..48]);
            return Err(format!(
                "written by build {}, this is {BUILD_ID}",
                theirs.trim_end_matches('\0')
            ));
        }
        let count = u32_at(96) as usize;
        if count > MAX_SECTIONS {
            return Err(format!("{count} sections"));
        }
        Ok(Self {
            kind: u32_at(12),
            layout: u128::from_le_bytes(h[48..64].try_into().unwrap_or_default()),
            options: [u64_at(64), u64_at(72)],
            payload_len: u64_at(80),
            checksum: u64_at(88),
            sections: (0..count).map(|k| u64_at(SECTIONS_AT + 8 * k)).collect(),
        })
    }
}

fn padded(len: u64) -> Option<u64> {
    len.checked_add(7).map(|n| n & !7)
}

/// Bytes of payload per checksum chunk.
const CHECKSUM_CHUNK: usize = 1 << 20;

/// The payload checksum: XXH3-64 of the XXH3-64s of its consecutive [`CHECKSUM_CHUNK`]-byte
/// chunks, so that a load hashes the chunks in parallel (format 1 hashed the payload in one
/// pass, on one thread).
fn payload_checksum(payload: &[u8]) -> u64 {
    let sums: Vec<u64> = payload.par_chunks(CHECKSUM_CHUNK).map(xxh3_64).collect();
    xxh3_64(bytemuck::cast_slice(&sums))
}

/// Writes sections (padded to 8 bytes) while hashing them as [`payload_checksum`] does.
pub(crate) struct SectionWriter<W: Write> {
    out: W,
    /// The current chunk's hash and length, and the sums of the chunks before it.
    chunk: Xxh3,
    in_chunk: usize,
    sums: Vec<u64>,
    lengths: Vec<u64>,
    written: u64,
}

impl<W: Write> SectionWriter<W> {
    fn new(out: W) -> Self {
        Self {
            out,
            chunk: Xxh3::new(),
            in_chunk: 0,
            sums: Vec::new(),
            lengths: Vec::new(),
            written: 0,
        }
    }

    fn raw(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.written += bytes.len() as u64;
        self.out.write_all(bytes)?;
        let mut rest = bytes;
        while !rest.is_empty() {
            let n = (CHECKSUM_CHUNK - self.in_chunk).min(rest.len());
            self.chunk.update(&rest[..n]);
            self.in_chunk += n;
            rest = &rest[n..];
            if self.in_chunk == CHECKSUM_CHUNK {
                self.sums.push(self.chunk.digest());
                self.chunk.reset();
                self.in_chunk = 0;
            }
        }
        Ok(())
    }

    fn pad(&mut self) -> io::Result<()> {
        let rem = (self.written % 8) as usize;
        if rem != 0 {
            self.raw(&[0u8; 8][rem..])?;
        }
        Ok(())
    }

    /// Start the next section.
    pub(crate) fn section(&mut self) -> io::Result<()> {
        self.pad()?;
        self.lengths.push(0);
        Ok(())
    }

    /// Append `bytes` to the current section.
    pub(crate) fn put(&mut self, bytes: &[u8]) -> io::Result<()> {
        if let Some(len) = self.lengths.last_mut() {
            *len += bytes.len() as u64;
        }
        self.raw(bytes)
    }

    fn finish(mut self) -> io::Result<(W, Vec<u64>, u64, u64)> {
        self.pad()?;
        if self.in_chunk > 0 {
            self.sums.push(self.chunk.digest());
        }
        let checksum = xxh3_64(bytemuck::cast_slice(&self.sums));
        Ok((self.out, self.lengths, self.written, checksum))
    }
}

/// The byte ranges (within the file, after a header of `HEADER_BYTES`) of the sections of a
/// `payload_len`-byte payload with these (unpadded) lengths.
fn split(payload_len: u64, lengths: &[u64]) -> Result<Vec<Range<usize>>, String> {
    let mut at = 0u64;
    let mut out = Vec::with_capacity(lengths.len());
    for &len in lengths {
        let end = at.checked_add(len).ok_or("section length overflows")?;
        if end > payload_len {
            return Err("a section runs past the end of the file".into());
        }
        out.push(HEADER_BYTES + at as usize..HEADER_BYTES + end as usize);
        at = padded(end).ok_or("section length overflows")?;
    }
    if at != payload_len {
        return Err("sections do not fill the payload".into());
    }
    Ok(out)
}

/// A mapped plan file whose header and checksum passed, and the ranges of its sections.
pub(crate) struct PlanFile {
    map: Arc<Mmap>,
    sections: Vec<Range<usize>>,
    /// Whether arrays may be read in place (see the module documentation), else copied.
    in_place: bool,
}

impl PlanFile {
    fn range(&self, k: usize) -> Result<Range<usize>, String> {
        self.sections
            .get(k)
            .cloned()
            .ok_or_else(|| format!("section {k} missing"))
    }

    /// Section `k` as a slice of `T` (length a whole number of elements, suitably aligned).
    fn view<T: bytemuck::Pod>(&self, k: usize, what: &str) -> Result<&[T], String> {
        let bytes = self
            .map
            .get(self.range(k)?)
            .ok_or("a section past the end")?;
        bytemuck::try_cast_slice(bytes).map_err(|e| format!("{what}: {e:?}"))
    }

    /// Section `k` as an array a map can keep: read in place if allowed, else a copy. The
    /// caller checks its contents before handing the map out.
    fn array<T: bytemuck::Pod>(&self, k: usize, what: &str) -> Result<PlanArray<T>, String> {
        if self.in_place {
            PlanArray::mapped(&self.map, self.range(k)?)
                .ok_or_else(|| format!("{what}: not a whole number of aligned elements"))
        } else {
            Ok(PlanArray::from(self.view::<T>(k, what)?.to_vec()))
        }
    }
}

/// Whether a plan file may be read in place for as long as a map lives: only if no one but
/// this process's user can change it (see the module documentation).
#[cfg(unix)]
fn only_we_can_write(meta: &fs::Metadata) -> bool {
    use std::os::unix::fs::MetadataExt;
    // SAFETY: geteuid has no preconditions and cannot fail.
    let me = unsafe { libc::geteuid() };
    meta.uid() == me && meta.mode() & 0o022 == 0
}

#[cfg(not(unix))]
fn only_we_can_write(_: &fs::Metadata) -> bool {
    false
}

/// The file of a map, or `Ok(None)` if there is none; `Err` says why a file was rejected.
pub(crate) fn load<T: StoredMap>(
    path: &Path,
    layout: &Layout,
    layout_hash: u128,
    options: [u64; 2],
    erp: Option<&ErpTaps>,
) -> Result<Option<T>, String> {
    let file = match File::open(path) {
        Ok(file) => file,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(format!("cannot open: {e}")),
    };
    let meta = file.metadata().map_err(|e| e.to_string())?;
    let len = meta.len();
    if len < HEADER_BYTES as u64 {
        return Err(format!("truncated ({len} bytes)"));
    }
    // SAFETY: m360 never modifies a plan file in place (new files are renamed over old ones,
    // which leaves this mapping intact); only someone truncating the file by hand while it is
    // mapped could invalidate the mapping, and a file read in place is one only this user can
    // write (`only_we_can_write`).
    // Not populated: the checksum reads every page in order and the kernel maps them in
    // batches around each fault; with the copy gone, populating measured no faster.
    let map = unsafe { MmapOptions::new().map(&file) }.map_err(|e| format!("cannot map: {e}"))?;
    let map = Arc::new(map);
    let header = Header::decode(&map[..HEADER_BYTES])?;
    if header.kind != T::KIND as u32 || header.layout != layout_hash || header.options != options {
        return Err("written for another map, layout or options".into());
    }
    let payload = &map[HEADER_BYTES..];
    if header.payload_len != payload.len() as u64 {
        return Err(format!(
            "payload is {} bytes, the header says {}",
            payload.len(),
            header.payload_len
        ));
    }
    if payload_checksum(payload) != header.checksum {
        return Err("payload checksum mismatch".into());
    }
    let sections = split(header.payload_len, &header.sections)?;
    let file = PlanFile {
        map,
        sections,
        in_place: only_we_can_write(&meta),
    };
    T::decode(&file, layout, erp).map(Some)
}

/// Write `map` to `path` atomically (temporary file in the same folder, synced, renamed).
pub(crate) fn save<T: StoredMap>(
    path: &Path,
    layout_hash: u128,
    options: [u64; 2],
    map: &T,
) -> io::Result<()> {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let dir = path.parent().unwrap_or(Path::new("."));
    fs::create_dir_all(dir)?;
    let name = path
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    let tmp: PathBuf = dir.join(format!(
        ".{name}.{}.{}.tmp",
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    ));
    let write = || -> io::Result<()> {
        let mut out = BufWriter::with_capacity(1 << 20, create_new(&tmp)?);
        out.write_all(&[0u8; HEADER_BYTES])?;
        let mut sections = SectionWriter::new(out);
        map.write(&mut sections)?;
        let (out, lengths, payload_len, checksum) = sections.finish()?;
        if lengths.len() > MAX_SECTIONS {
            return Err(io::Error::other("too many sections"));
        }
        let header = Header {
            kind: T::KIND as u32,
            layout: layout_hash,
            options,
            payload_len,
            checksum,
            sections: lengths,
        };
        let mut file = out.into_inner().map_err(io::IntoInnerError::into_error)?;
        file.seek(SeekFrom::Start(0))?;
        file.write_all(&header.encode())?;
        file.sync_all()?;
        drop(file);
        fs::rename(&tmp, path)?;
        // Make the rename itself durable (not possible on every platform: best effort).
        if let Ok(folder) = File::open(dir) {
            drop(folder.sync_all());
        }
        Ok(())
    };
    let result = write();
    if result.is_err() {
        drop(fs::remove_file(&tmp));
    }
    result
}

/// A new file at `path`, writable by its owner only whatever the umask allows more (so that
/// the file can be read in place later; see [`only_we_can_write`]).
fn create_new(path: &Path) -> io::Result<File> {
    let mut options = fs::OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o644);
    options.open(path)
}

impl StoredMap for TangentTaps {
    const KIND: Kind = Kind::TangentTaps;

    fn is_mapped(&self) -> bool {
        TangentTaps::is_mapped(self)
    }

    fn write<W: Write>(&self, out: &mut SectionWriter<W>) -> io::Result<()> {
        let (taps, wrapped) = self.parts();
        out.section()?;
        out.put(bytemuck::cast_slice(taps))?;
        out.section()?;
        out.put(bytemuck::cast_slice(wrapped))
    }

    fn decode(file: &PlanFile, layout: &Layout, _: Option<&ErpTaps>) -> Result<Self, String> {
        let (h, w) = layout.tangent_shape();
        let (eh, ew) = (layout.erp_height, layout.erp_width);
        let taps = file.array::<Tap>(0, "tangent taps")?;
        let wrapped = file.array::<[u32; 4]>(1, "wrapped corners")?;
        if taps.len() != layout.cameras.len() * h * w {
            return Err(format!(
                "{} tangent taps, the layout has {} pixels",
                taps.len(),
                layout.cameras.len() * h * w
            ));
        }
        if wrapped.iter().flatten().any(|&k| k as usize >= eh * ew) {
            return Err("a wrapped corner outside the ERP grid".into());
        }
        let in_grid = |tap: &Tap| {
            tap.fractions_in_range()
                && if tap.index & WRAPPED == 0 {
                    let i = tap.index as usize;
                    i % ew + 1 < ew && i / ew + 1 < eh
                } else {
                    ((tap.index & !WRAPPED) as usize) < wrapped.len()
                }
        };
        if !taps
            .par_chunks(1 << 14)
            .all(|chunk| chunk.iter().all(in_grid))
        {
            return Err("a tangent tap outside the ERP grid".into());
        }
        Ok(TangentTaps::from_parts(taps, wrapped, eh, ew))
    }
}

impl StoredMap for ErpTaps {
    const KIND: Kind = Kind::ErpTaps;

    fn is_mapped(&self) -> bool {
        ErpTaps::is_mapped(self)
    }

    fn write<W: Write>(&self, out: &mut SectionWriter<W>) -> io::Result<()> {
        out.section()?;
        out.put(self.counts())?;
        out.section()?;
        let runs_per_row: Vec<u32> = (0..self.rows())
            .map(|i| self.row_parts(i).0.len() as u32)
            .collect();
        out.put(bytemuck::cast_slice(&runs_per_row))?;
        out.section()?;
        for i in 0..self.rows() {
            out.put(bytemuck::cast_slice(self.row_parts(i).0))?;
        }
        out.section()?;
        for i in 0..self.rows() {
            out.put(bytemuck::cast_slice(self.row_parts(i).1))?;
        }
        Ok(())
    }

    fn decode(file: &PlanFile, layout: &Layout, _: Option<&ErpTaps>) -> Result<Self, String> {
        let (eh, ew) = (layout.erp_height, layout.erp_width);
        let counts = file.array::<u8>(0, "counts")?;
        let runs_per_row: &[u32] = file.view(1, "runs per row")?;
        let runs = file.array::<Run>(2, "runs")?;
        let taps = file.array::<Tap>(3, "ERP taps")?;
        if counts.len() != eh * ew || runs_per_row.len() != eh {
            return Err("counts or rows do not match the ERP size".into());
        }
        // Where each row's runs and taps start.
        let mut run_at = Vec::with_capacity(eh + 1);
        let mut total = 0usize;
        for &n in runs_per_row {
            run_at.push(total);
            total += n as usize;
        }
        run_at.push(total);
        if total != runs.len() {
            return Err("run counts do not add up".into());
        }
        let mut tap_at = Vec::with_capacity(eh + 1);
        let mut total = 0u64;
        for i in 0..eh {
            tap_at.push(total as usize);
            total += runs[run_at[i]..run_at[i + 1]]
                .iter()
                .map(|r| u64::from(r.len))
                .sum::<u64>();
        }
        tap_at.push(total as usize);
        if total != taps.len() as u64 {
            return Err("tap counts do not add up".into());
        }
        (0..eh).into_par_iter().try_for_each(|i| {
            check_erp_row(
                layout,
                &runs[run_at[i]..run_at[i + 1]],
                &taps[tap_at[i]..tap_at[i + 1]],
                &counts[i * ew..(i + 1) * ew],
            )
            .map_err(|e| format!("ERP row {i}: {e}"))
        })?;
        Ok(ErpTaps::from_parts(
            layout,
            counts,
            (runs, run_at),
            (taps, tap_at),
        ))
    }
}

/// Check one ERP row's runs and taps: runs sorted by face then column, inside the row, their
/// taps consecutive; the per-pixel counts those of the runs; every tap inside its face with a
/// rank below its pixel's count and fractions of at most one pixel.
fn check_erp_row(
    layout: &Layout,
    runs: &[Run],
    taps: &[Tap],
    counts: &[u8],
) -> Result<(), &'static str> {
    let (h, w) = layout.tangent_shape();
    let (ew, faces) = (layout.erp_width, layout.cameras.len());
    let mut seen = vec![0u8; ew];
    let mut next_tap = 0usize;
    let mut previous: Option<(u32, u64)> = None;
    for run in runs {
        let Run {
            face,
            start,
            len,
            start_tap,
        } = *run;
        let end = u64::from(start) + u64::from(len);
        if face as usize >= faces || len == 0 || end > ew as u64 {
            return Err("a run outside the layout or the row");
        }
        if start_tap as usize != next_tap {
            return Err("runs' taps are not consecutive");
        }
        if let Some((f, e)) = previous {
            if face < f || (face == f && u64::from(start) < e) {
                return Err("runs out of order");
            }
        }
        previous = Some((face, end));
        let run_taps = taps
            .get(next_tap..next_tap + len as usize)
            .ok_or("fewer taps than the runs need")?;
        for (j, tap) in (start as usize..end as usize).zip(run_taps) {
            if !tap.fractions_in_range() {
                return Err("a tap fraction above one");
            }
            let offset = (tap.index & OFFSET_MASK) as usize;
            let rank = tap.index >> RANK_SHIFT;
            if offset % w + 1 >= w || offset / w + 1 >= h || rank >= u32::from(counts[j]) {
                return Err("a tap outside its face");
            }
            seen[j] = seen[j].checked_add(1).ok_or("too many taps at a pixel")?;
        }
        next_tap += len as usize;
    }
    if next_tap != taps.len() || seen != counts {
        return Err("counts do not match the runs");
    }
    Ok(())
}

impl StoredMap for Overlaps {
    const KIND: Kind = Kind::Overlaps;

    fn write<W: Write>(&self, out: &mut SectionWriter<W>) -> io::Result<()> {
        for part in self.parts() {
            out.section()?;
            out.put(part)?;
        }
        Ok(())
    }

    // Small (about a megabyte at 8K): copied.
    fn decode(file: &PlanFile, layout: &Layout, _: Option<&ErpTaps>) -> Result<Self, String> {
        let (h, w) = layout.tangent_shape();
        let faces = layout.cameras.len();
        let a: &[u16] = file.view(0, "overlap faces a")?;
        let b: &[u16] = file.view(1, "overlap faces b")?;
        let pa: &[u32] = file.view(2, "overlap pixels")?;
        let xb: &[f32] = file.view(3, "overlap columns")?;
        let yb: &[f32] = file.view(4, "overlap rows")?;
        let n = a.len();
        if [b.len(), pa.len(), xb.len(), yb.len()] != [n; 4] {
            return Err("overlap arrays of different lengths".into());
        }
        let ok = (0..n).into_par_iter().all(|k| {
            (a[k] as usize) < faces
                && (b[k] as usize) < faces
                && (pa[k] as usize) < h * w
                && (0.0..=(w - 1) as f32).contains(&xb[k])
                && (0.0..=(h - 1) as f32).contains(&yb[k])
        });
        if !ok {
            return Err("an overlap sample outside the layout".into());
        }
        Ok(Overlaps::from_parts(
            a.to_vec(),
            b.to_vec(),
            pa.to_vec(),
            xb.to_vec(),
            yb.to_vec(),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::blend::Method;
    use crate::plan::{Need, Plan};

    fn fresh_dir(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("m360-plan-cache-{name}-{}", std::process::id()));
        drop(fs::remove_dir_all(&dir));
        fs::create_dir_all(&dir).expect("temp dir");
        dir
    }

    fn needs() -> Vec<Need> {
        vec![Need::TangentTaps, Need::ErpTaps, Need::Overlaps(0.01, 5.0)]
    }

    fn cached_plan(layout: &Layout, dir: &Path) -> Plan {
        let plan = Plan::new(layout.clone());
        plan.set_disk_cache(Some(dir.to_path_buf()));
        plan.prepare(&needs(), |build| build());
        plan
    }

    /// (name, bytes) of every plan file in `dir`, sorted.
    fn files(dir: &Path) -> Vec<(String, Vec<u8>)> {
        let mut out: Vec<_> = fs::read_dir(dir)
            .expect("dir")
            .flatten()
            .map(|e| {
                let name = e.file_name().to_string_lossy().into_owned();
                (name, fs::read(e.path()).expect("read"))
            })
            .collect();
        out.sort();
        out
    }

    /// A deterministic tangent stack with some NaN (invalid) pixels.
    fn tangents(layout: &Layout) -> Vec<f32> {
        let (h, w) = layout.tangent_shape();
        let mut state = 0x9e37_79b9_7f4a_7c15_u64;
        (0..layout.cameras.len() * h * w)
            .map(|_| {
                state = state
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1);
                let v = (state >> 40) as f32 / (1u64 << 24) as f32;
                if v < 0.02 {
                    f32::NAN
                } else {
                    0.5 + v
                }
            })
            .collect()
    }

    /// A deterministic ERP image sampled into the tangents through the plan's tangent taps.
    fn sampled(plan: &Plan) -> Vec<u32> {
        let layout = plan.layout();
        let (h, w) = layout.tangent_shape();
        let erp: Vec<f32> = (0..layout.erp_height * layout.erp_width)
            .map(|k| (k % 977) as f32 * 0.25)
            .collect();
        let mut out = vec![0f32; layout.cameras.len() * h * w];
        plan.tangent_taps().sample::<f32, 1>(&erp, &mut out, w);
        out.iter().map(|v| v.to_bits()).collect()
    }

    fn blended(plan: &Plan, method: &Method) -> Vec<u32> {
        let layout = plan.layout();
        let mut out = vec![0f32; layout.erp_height * layout.erp_width];
        plan.blend(&tangents(layout), method, &mut out, None)
            .expect("blend");
        out.iter().map(|v| v.to_bits()).collect()
    }

    /// Saving the maps of a plan that loaded them writes byte-identical files: every stored
    /// field survives the round trip. Blends through loaded maps are bit-identical too.
    #[test]
    fn loaded_maps_equal_built_ones() {
        let layout = Layout::icosahedron(128, 0.3, None).expect("layout");
        let dir = fresh_dir("round-trip");
        let built = cached_plan(&layout, &dir);
        let stats = built.disk_stats();
        assert_eq!(
            (stats.loaded, stats.built, stats.saved, stats.rejected),
            (0, 3, 3, 0)
        );
        let written = files(&dir);
        assert_eq!(written.len(), 3);

        let loaded = cached_plan(&layout, &dir);
        let stats = loaded.disk_stats();
        assert_eq!(
            (stats.loaded, stats.built, stats.saved, stats.rejected),
            (3, 0, 0, 0)
        );
        // On Unix the taps read their files in place (the overlaps are copied).
        assert_eq!(stats.mapped, if cfg!(unix) { 2 } else { 0 });
        assert_eq!(loaded.erp_taps().is_mapped(), cfg!(unix));
        assert!(!built.erp_taps().is_mapped());
        for method in [Method::Frustum, Method::Radial, Method::Mean] {
            assert_eq!(blended(&built, &method), blended(&loaded, &method));
        }
        assert_eq!(sampled(&built), sampled(&loaded));
        let again = fresh_dir("round-trip-again");
        let hash = layout_hash(&layout);
        let path = |kind, options| again.join(file_name(kind, &layout, hash, options));
        let fraction = (0.01f64.to_bits(), 5.0f64.to_bits());
        save(
            &path(Kind::TangentTaps, [0; 2]),
            hash,
            [0; 2],
            loaded.tangent_taps(),
        )
        .expect("save");
        save(
            &path(Kind::ErpTaps, [0; 2]),
            hash,
            [0; 2],
            loaded.erp_taps(),
        )
        .expect("save");
        let overlaps = loaded.overlaps(0.01, 5.0);
        let options = [fraction.0, fraction.1];
        save(&path(Kind::Overlaps, options), hash, options, &*overlaps).expect("save");
        assert_eq!(files(&again), written);
        drop((fs::remove_dir_all(dir), fs::remove_dir_all(again)));
    }

    /// Recompute the payload and header checksums after editing a file by hand.
    fn reseal(bytes: &mut [u8]) {
        let sum = payload_checksum(&bytes[HEADER_BYTES..]);
        bytes[88..96].copy_from_slice(&sum.to_le_bytes());
        let sum = xxh3_64(&bytes[..HEADER_SUM_AT]);
        bytes[HEADER_SUM_AT..HEADER_BYTES].copy_from_slice(&sum.to_le_bytes());
    }

    type Damage = Box<dyn Fn(&mut Vec<u8>)>;

    /// (what, the reason the loader must give, how) for each kind of damage to an ERP taps file.
    fn damages() -> Vec<(&'static str, &'static str, Damage)> {
        vec![
            (
                "truncated",
                "payload is",
                Box::new(|b: &mut Vec<u8>| b.truncate(b.len() / 2)),
            ),
            (
                "header only, cut",
                "truncated",
                Box::new(|b: &mut Vec<u8>| b.truncate(100)),
            ),
            ("empty", "truncated", Box::new(|b: &mut Vec<u8>| b.clear())),
            (
                "flipped payload byte",
                "payload checksum",
                Box::new(|b: &mut Vec<u8>| {
                    let at = b.len() - b.len() / 3;
                    b[at] ^= 0x10;
                }),
            ),
            (
                "random bytes",
                "no magic",
                Box::new(|b: &mut Vec<u8>| {
                    let mut state = 12345u64;
                    for v in b.iter_mut() {
                        state = state
                            .wrapping_mul(6_364_136_223_846_793_005)
                            .wrapping_add(1);
                        *v = (state >> 56) as u8;
                    }
                }),
            ),
            (
                "other format version",
                "file format",
                Box::new(|b: &mut Vec<u8>| {
                    b[8..12].copy_from_slice(&(FORMAT_VERSION + 1).to_le_bytes());
                    reseal(b);
                }),
            ),
            (
                "other build",
                "written by build",
                Box::new(|b: &mut Vec<u8>| {
                    b[16] ^= 1;
                    reseal(b);
                }),
            ),
            (
                "appended bytes",
                "payload is",
                Box::new(|b: &mut Vec<u8>| b.extend([0u8; 8])),
            ),
            // Valid checksums, but a tap index far outside its face: bounds validation.
            (
                "index out of bounds, resealed",
                "a tap outside its face",
                Box::new(|b: &mut Vec<u8>| {
                    let last = b.len() - 8;
                    b[last..last + 4].copy_from_slice(&0x0fff_fff0_u32.to_le_bytes());
                    reseal(b);
                }),
            ),
            // Valid checksums, but a tap's fractions above one pixel.
            (
                "fraction above one, resealed",
                "a tap fraction above one",
                Box::new(|b: &mut Vec<u8>| {
                    let last = b.len() - 4;
                    b[last..].copy_from_slice(&0xffff_ffff_u32.to_le_bytes());
                    reseal(b);
                }),
            ),
            // A run starting past the row's end.
            (
                "run past the row, resealed",
                "a run outside",
                Box::new(|b: &mut Vec<u8>| {
                    let sections: Vec<u64> = (0..4)
                        .map(|k| {
                            let at = SECTIONS_AT + 8 * k;
                            u64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"))
                        })
                        .collect();
                    let runs_at = HEADER_BYTES as u64
                        + padded(sections[0]).expect("pad")
                        + padded(sections[1]).expect("pad");
                    let start_at = runs_at as usize + 4;
                    b[start_at..start_at + 4].copy_from_slice(&0xffff_0000_u32.to_le_bytes());
                    reseal(b);
                }),
            ),
        ]
    }

    /// Every kind of damage is detected: the map is rebuilt and rewritten (the file then equals
    /// the original again) and the plan says why.
    #[test]
    fn damaged_files_are_rebuilt_never_trusted() {
        let layout = Layout::icosahedron(96, 0.3, None).expect("layout");
        let dir = fresh_dir("damaged");
        let reference = cached_plan(&layout, &dir);
        let original = files(&dir);
        let erp_taps = original
            .iter()
            .find(|(name, _)| name.starts_with("erp-taps"))
            .expect("erp taps file")
            .clone();
        let path = dir.join(&erp_taps.0);
        for (what, reason, damage) in damages() {
            let mut bytes = erp_taps.1.clone();
            damage(&mut bytes);
            fs::write(&path, &bytes).expect("write");
            let plan = Plan::new(layout.clone());
            plan.set_disk_cache(Some(dir.clone()));
            plan.prepare(&[Need::ErpTaps], |build| build());
            let stats = plan.disk_stats();
            assert_eq!(
                (stats.rejected, stats.built, stats.saved),
                (1, 1, 1),
                "{what}"
            );
            let notes = plan.take_disk_notes();
            assert!(
                notes.len() == 1 && notes[0].contains(reason),
                "{what}: {notes:?}"
            );
            assert_eq!(
                fs::read(&path).expect("read"),
                erp_taps.1,
                "{what}: rewritten"
            );
            assert_eq!(
                blended(&plan, &Method::Mean),
                blended(&reference, &Method::Mean)
            );
        }
        assert_eq!(files(&dir), original, "no temporary files left");
        drop(fs::remove_dir_all(dir));
    }

    /// A tangent taps file with valid checksums but a tap outside the ERP grid is refused.
    #[test]
    fn a_tangent_tap_outside_the_grid_is_refused() {
        let layout = Layout::icosahedron(96, 0.3, None).expect("layout");
        let dir = fresh_dir("tangent-damage");
        drop(cached_plan(&layout, &dir));
        let path = dir.join(file_name(
            Kind::TangentTaps,
            &layout,
            layout_hash(&layout),
            [0; 2],
        ));
        let original = fs::read(&path).expect("read");
        for (at, word, reason) in [
            (HEADER_BYTES, 0x7fff_fff0_u32, "outside the ERP grid"),
            (HEADER_BYTES + 4, 0xffff_ffff_u32, "outside the ERP grid"),
            (HEADER_BYTES, WRAPPED | 0x00ff_ffff, "outside the ERP grid"),
        ] {
            let mut bytes = original.clone();
            bytes[at..at + 4].copy_from_slice(&word.to_le_bytes());
            reseal(&mut bytes);
            fs::write(&path, &bytes).expect("write");
            let plan = Plan::new(layout.clone());
            plan.set_disk_cache(Some(dir.clone()));
            plan.prepare(&[Need::TangentTaps], |build| build());
            let notes = plan.take_disk_notes();
            assert_eq!(plan.disk_stats().rejected, 1, "{word:#x}");
            assert!(notes[0].contains(reason), "{notes:?}");
            assert_eq!(fs::read(&path).expect("read"), original, "rewritten");
        }
        drop(fs::remove_dir_all(dir));
    }

    /// A file that others could change while it is mapped is copied into memory, not read in
    /// place, and gives the same maps.
    #[cfg(unix)]
    #[test]
    fn a_file_others_can_write_is_copied() {
        use std::os::unix::fs::PermissionsExt;
        let layout = Layout::icosahedron(96, 0.3, None).expect("layout");
        let dir = fresh_dir("group-writable");
        let built = cached_plan(&layout, &dir);
        for (name, _) in files(&dir) {
            fs::set_permissions(dir.join(name), fs::Permissions::from_mode(0o664)).expect("chmod");
        }
        let copied = cached_plan(&layout, &dir);
        let stats = copied.disk_stats();
        assert_eq!((stats.loaded, stats.mapped, stats.built), (3, 0, 0));
        assert!(!copied.erp_taps().is_mapped());
        assert_eq!(
            blended(&built, &Method::Frustum),
            blended(&copied, &Method::Frustum)
        );
        assert_eq!(sampled(&built), sampled(&copied));
        drop(fs::remove_dir_all(dir));
    }

    /// A file of another layout (renamed into place) is refused by its header.
    #[test]
    fn a_file_of_another_layout_is_refused() {
        let (small, big) = (
            Layout::icosahedron(64, 0.3, None).expect("layout"),
            Layout::icosahedron(96, 0.3, None).expect("layout"),
        );
        let dir = fresh_dir("foreign");
        drop(cached_plan(&small, &dir));
        let source = dir.join(file_name(
            Kind::TangentTaps,
            &small,
            layout_hash(&small),
            [0; 2],
        ));
        let target = dir.join(file_name(
            Kind::TangentTaps,
            &big,
            layout_hash(&big),
            [0; 2],
        ));
        fs::copy(source, &target).expect("copy");
        let plan = Plan::new(big);
        plan.set_disk_cache(Some(dir.clone()));
        plan.prepare(&[Need::TangentTaps], |build| build());
        assert_eq!(plan.disk_stats().rejected, 1);
        drop(fs::remove_dir_all(dir));
    }

    /// The writer's chunked checksum is the loader's, whatever the chunk boundaries of the
    /// writes (checked against one-shot XXH3 of each chunk).
    #[test]
    fn written_checksums_are_the_chunked_checksum() {
        let bytes: Vec<u8> = (0..3 * CHECKSUM_CHUNK + 12_345)
            .map(|k| (k * 31 % 251) as u8)
            .collect();
        for piece in [1000, CHECKSUM_CHUNK, CHECKSUM_CHUNK + 7, bytes.len()] {
            let mut writer = SectionWriter::new(Vec::new());
            writer.section().expect("section");
            for part in bytes.chunks(piece) {
                writer.put(part).expect("put");
            }
            let (out, _, written, checksum) = writer.finish().expect("finish");
            assert_eq!(written as usize, out.len());
            let sums: Vec<u64> = out.chunks(CHECKSUM_CHUNK).map(xxh3_64).collect();
            assert_eq!(checksum, xxh3_64(bytemuck::cast_slice(&sums)), "{piece}");
            assert_eq!(checksum, payload_checksum(&out));
        }
    }

    #[test]
    fn without_a_folder_nothing_is_written() {
        let plan = Plan::new(Layout::icosahedron(64, 0.3, None).expect("layout"));
        plan.prepare(&needs(), |build| build());
        let stats = plan.disk_stats();
        assert_eq!((stats.loaded, stats.built, stats.saved), (0, 3, 0));
    }
}
