//! Per-(layout, ERP size) sampling maps, built once and shared by every later image.
//!
//! # Building without deadlocks
//!
//! The maps are built with rayon, and a plan is shared by threads that each run work on the
//! same pool. A lazily initialised value whose initialiser runs parallel work must never be
//! waited for from *inside* the pool: while a worker builds, it steals other queued jobs, and a
//! stolen job that waits for the same value blocks the very thread that is building it (all
//! threads then sleep in a futex). So:
//!
//! - [`Plan::prepare`] builds what an operation needs. It is meant to be called from outside the
//!   pool (the bindings call it before entering the pool); it holds the plan's build lock on
//!   the calling thread only while the pool runs the build, and no job inside the pool ever
//!   takes that lock.
//! - The getters ([`Plan::erp_taps`] …) never wait: they return the built map, or, if called
//!   before `prepare` (core tests, or from inside a pool), build it right there without any
//!   lock; if two threads race, both build and the first stored copy wins.
//!
//! # Disk cache
//!
//! With a folder set ([`Plan::set_disk_cache`]), every map is first looked up there and every
//! map built is written there (see [`crate::plan_cache`]); a file that fails any check is
//! rebuilt and rewritten, and the reason kept for the caller ([`Plan::take_disk_notes`]).
//! Loading and saving take no lock that a build holds, so the rules above are unchanged.

use crate::align::Overlaps;
use crate::blend::{self, BlendReport, Method, WeightMaps, Weighting};
use crate::error::Result;
use crate::layout::Layout;
use crate::options::Choice;
use crate::plan_cache::{self, StoredMap};
use crate::resample::{ErpTaps, TangentTaps};
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};

/// (sample fraction, pole cap) as bit patterns: the options overlap samples depend on.
type OverlapKey = (u64, u64);

/// A map of a plan that an operation needs built.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Need {
    /// Where each tangent pixel samples the ERP image.
    TangentTaps,
    /// Which tangents, and where, each ERP pixel sees.
    ErpTaps,
    /// Blending weights of a kind as per-face maps, what the blends read.
    WeightMaps(Weighting),
    /// Overlap samples for alignment with (sample fraction, pole cap in degrees).
    Overlaps(f64, f64),
}

/// Everything that depends only on the layout (and so on the ERP size), not on the image.
#[derive(Debug)]
pub struct Plan {
    layout: Layout,
    tangent_taps: OnceLock<TangentTaps>,
    erp_taps: OnceLock<ErpTaps>,
    /// Overlap samples per (sample fraction, pole cap) — a handful of option sets at most.
    overlaps: Mutex<Vec<(OverlapKey, Arc<Overlaps>)>>,
    /// Weights at every ERP tap, per [`Weighting`] (the weight maps themselves are not kept:
    /// the blends only ever read them at the taps).
    weight_maps: [OnceLock<WeightMaps>; 4],
    /// Held by [`Plan::prepare`] while it builds, so concurrent callers build each map once.
    building: Mutex<()>,
    /// Hash of the layout that names its files in the disk cache.
    layout_hash: u128,
    /// Folder of the disk cache; `None`: maps are only built, never loaded or saved.
    disk: Mutex<Option<PathBuf>>,
    /// Why cache files were rejected or could not be written, until the caller takes them.
    disk_notes: Mutex<Vec<String>>,
    /// Maps loaded, built, saved, files rejected, and maps loaded that read their file in place.
    disk_counts: [AtomicUsize; 5],
}

/// What a plan's maps came from so far (see [`Plan::disk_stats`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DiskStats {
    /// Maps loaded from the disk cache.
    pub loaded: usize,
    /// Maps built (with or without a disk cache).
    pub built: usize,
    /// Maps written to the disk cache.
    pub saved: usize,
    /// Cache files rejected (then rebuilt and rewritten).
    pub rejected: usize,
    /// Maps loaded that read their file in place, memory-mapped (the others were copied).
    pub mapped: usize,
}

impl Plan {
    /// A plan for `layout`; no map is built yet.
    #[must_use]
    pub fn new(layout: Layout) -> Self {
        Self {
            tangent_taps: OnceLock::new(),
            erp_taps: OnceLock::new(),
            overlaps: Mutex::new(Vec::new()),
            weight_maps: Default::default(),
            building: Mutex::new(()),
            layout_hash: plan_cache::layout_hash(&layout),
            layout,
            disk: Mutex::new(None),
            disk_notes: Mutex::new(Vec::new()),
            disk_counts: Default::default(),
        }
    }

    /// Keep maps in the folder `dir` (load before building, save after), or not (`None`).
    pub fn set_disk_cache(&self, dir: Option<PathBuf>) {
        *self.disk.lock().unwrap_or_else(PoisonError::into_inner) = dir;
    }

    /// The folder of the disk cache, if any.
    pub fn disk_cache(&self) -> Option<PathBuf> {
        self.disk
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// What the maps built so far came from.
    pub fn disk_stats(&self) -> DiskStats {
        let [loaded, built, saved, rejected, mapped] = self
            .disk_counts
            .each_ref()
            .map(|c| c.load(Ordering::Relaxed));
        DiskStats {
            loaded,
            built,
            saved,
            rejected,
            mapped,
        }
    }

    /// The reasons cache files were rejected or not written since the last call.
    pub fn take_disk_notes(&self) -> Vec<String> {
        std::mem::take(
            &mut *self
                .disk_notes
                .lock()
                .unwrap_or_else(PoisonError::into_inner),
        )
    }

    /// The path of the cache file of a map of `kind` with `options`, if the cache is on.
    pub fn disk_path(&self, kind: plan_cache::Kind, options: [u64; 2]) -> Option<PathBuf> {
        self.disk_cache().map(|dir| {
            dir.join(plan_cache::file_name(
                kind,
                &self.layout,
                self.layout_hash,
                options,
            ))
        })
    }

    fn note(&self, note: String) {
        self.disk_notes
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(note);
    }

    /// The map of `T` with `options` from the disk cache, else built by `build` (and saved).
    fn load_or_build<T: StoredMap>(
        &self,
        options: [u64; 2],
        erp: Option<&ErpTaps>,
        build: impl FnOnce() -> T,
    ) -> T {
        let count = |k: usize| self.disk_counts[k].fetch_add(1, Ordering::Relaxed);
        let path = self.disk_path(T::KIND, options);
        if let Some(path) = &path {
            match plan_cache::load::<T>(path, &self.layout, self.layout_hash, options, erp) {
                Ok(Some(map)) => {
                    count(0);
                    if map.is_mapped() {
                        count(4);
                    }
                    return map;
                }
                Ok(None) => {}
                Err(why) => {
                    count(3);
                    self.note(format!(
                        "plan cache file {} rejected ({why}); rebuilt",
                        path.display()
                    ));
                }
            }
        }
        let map = build();
        count(1);
        if let Some(path) = &path {
            match plan_cache::save(path, self.layout_hash, options, &map) {
                Ok(()) => drop(count(2)),
                Err(e) => self.note(format!(
                    "plan cache file {} not written: {e}",
                    path.display()
                )),
            }
        }
        map
    }

    /// The layout this plan serves.
    pub fn layout(&self) -> &Layout {
        &self.layout
    }

    /// Build the maps in `needs` that are not built yet, each once however many threads ask.
    ///
    /// `run` runs a build (typically `|build| pool.install(build)`). Call this from outside the
    /// pool that `run` uses (see the module documentation); from inside a rayon pool it builds
    /// without taking the lock.
    pub fn prepare(&self, needs: &[Need], run: impl Fn(&(dyn Fn() + Sync))) {
        let missing = |need: &Need| !self.is_built(*need);
        if !needs.iter().any(missing) {
            return;
        }
        if rayon::current_thread_index().is_some() {
            for &need in needs {
                self.build(need);
            }
            return;
        }
        // Poisoning only means another thread panicked mid-build: the maps stay valid.
        let _guard = self.building.lock().unwrap_or_else(PoisonError::into_inner);
        for need in needs.iter().filter(|n| missing(n)) {
            run(&|| self.build(*need));
        }
    }

    fn is_built(&self, need: Need) -> bool {
        match need {
            Need::TangentTaps => self.tangent_taps.get().is_some(),
            Need::ErpTaps => self.erp_taps.get().is_some(),
            Need::WeightMaps(kind) => self.weight_maps[weight_slot(kind)].get().is_some(),
            Need::Overlaps(fraction, cap) => self.cached_overlaps(fraction, cap).is_some(),
        }
    }

    fn build(&self, need: Need) {
        match need {
            Need::TangentTaps => drop(self.tangent_taps()),
            Need::ErpTaps => drop(self.erp_taps()),
            Need::WeightMaps(kind) => drop(self.weight_maps(kind)),
            Need::Overlaps(fraction, cap) => drop(self.overlaps(fraction, cap)),
        }
    }

    /// Where each tangent pixel samples the ERP image.
    pub fn tangent_taps(&self) -> &TangentTaps {
        get_or_build(&self.tangent_taps, || {
            self.load_or_build([0; 2], None, || TangentTaps::build(&self.layout))
        })
    }

    /// Which tangents, and where, each ERP pixel sees.
    pub fn erp_taps(&self) -> &ErpTaps {
        get_or_build(&self.erp_taps, || {
            self.load_or_build([0; 2], None, || ErpTaps::build(&self.layout))
        })
    }

    /// Blending weights of `kind` as per-face maps (cheap to compute: built, never cached on
    /// disk).
    pub fn weight_maps(&self, kind: Weighting) -> &WeightMaps {
        get_or_build(&self.weight_maps[weight_slot(kind)], || {
            WeightMaps::new(&self.layout, kind)
        })
    }

    fn cached_overlaps(&self, fraction: f64, pole_cap_deg: f64) -> Option<Arc<Overlaps>> {
        let key = (fraction.to_bits(), pole_cap_deg.to_bits());
        let cache = self.overlaps.lock().unwrap_or_else(PoisonError::into_inner);
        cache
            .iter()
            .find(|(k, _)| *k == key)
            .map(|(_, o)| o.clone())
    }

    /// Overlap samples for alignment with these options.
    pub fn overlaps(&self, fraction: f64, pole_cap_deg: f64) -> Arc<Overlaps> {
        if let Some(found) = self.cached_overlaps(fraction, pole_cap_deg) {
            return found;
        }
        // Built with the cache unlocked (the build runs parallel work); a racing copy is dropped.
        let key = (fraction.to_bits(), pole_cap_deg.to_bits());
        let built = Arc::new(self.load_or_build([key.0, key.1], None, || {
            Overlaps::build(&self.layout, fraction, pole_cap_deg)
        }));
        let mut cache = self.overlaps.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some((_, found)) = cache.iter().find(|(k, _)| *k == key) {
            return found.clone();
        }
        cache.push((key, built.clone()));
        built
    }

    /// The maps [`Plan::blend`] reads for `method`.
    pub fn blend_needs(method: &Method) -> Vec<Need> {
        let mut needs = vec![Need::ErpTaps];
        needs.extend(method.weighting().map(Need::WeightMaps));
        needs
    }

    /// Blend per-tangent maps (N·h·w, NaN = invalid) onto the ERP grid with `method`:
    /// `disparity` (H·W) gets the blend, NaN where no face has a valid sample; `confidence`
    /// (H·W, if given) the population standard deviation of the valid samples at each pixel.
    ///
    /// # Errors
    /// The Poisson blend's options or solve failures (see [`blend::poisson_blend`]).
    ///
    /// # Panics
    /// If the slices do not have the plan's sizes.
    pub fn blend(
        &self,
        tangents: &[f32],
        method: &Method,
        disparity: &mut [f32],
        confidence: Option<&mut [f32]>,
    ) -> Result<BlendReport> {
        self.blend_with_prior(tangents, method, None, disparity, confidence)
    }

    /// [`Plan::blend`] with the global prior's vote (the consensus blend's, and the Poisson
    /// blend's consensus target: [`blend::PriorVote`]; the other methods ignore it). With every
    /// method the confidence, if asked for, then includes the disagreement with the prior
    /// ([`blend::combine_confidence_with_prior`]).
    ///
    /// # Errors
    /// Those of [`Plan::blend`].
    ///
    /// # Panics
    /// If the slices do not have the plan's sizes.
    pub fn blend_with_prior(
        &self,
        tangents: &[f32],
        method: &Method,
        prior: Option<&blend::PriorVote<'_>>,
        disparity: &mut [f32],
        mut confidence: Option<&mut [f32]>,
    ) -> Result<BlendReport> {
        let report = self.blend_only(
            tangents,
            method,
            prior,
            disparity,
            confidence.as_deref_mut(),
        )?;
        if let (Some(vote), Some(conf)) = (prior, confidence) {
            blend::combine_confidence_with_prior(vote, disparity, conf, self.layout.erp_width);
        }
        Ok(report)
    }

    /// [`Plan::blend_with_prior`] without the prior in the confidence.
    fn blend_only(
        &self,
        tangents: &[f32],
        method: &Method,
        prior: Option<&blend::PriorVote<'_>>,
        disparity: &mut [f32],
        confidence: Option<&mut [f32]>,
    ) -> Result<BlendReport> {
        let (taps, layout) = (self.erp_taps(), &self.layout);
        let poisson = match method {
            Method::Mean => {
                blend::mean_blend(taps, layout, tangents, disparity, confidence);
                None
            }
            Method::Nearest => {
                blend::nearest_blend(taps, layout, tangents, disparity, confidence);
                None
            }
            Method::Frustum | Method::Radial => {
                let kind = if *method == Method::Radial {
                    Weighting::Radial
                } else {
                    Weighting::Frustum
                };
                let weights = self.weight_maps(kind);
                blend::weighted_blend(taps, layout, tangents, weights, disparity, confidence);
                None
            }
            Method::Consensus => {
                let weights = self.weight_maps(Weighting::Frustum);
                blend::consensus_blend_with_prior(
                    taps, layout, tangents, weights, prior, disparity, confidence,
                );
                None
            }
            Method::Median => {
                let weights = self.weight_maps(Weighting::Frustum);
                blend::median_blend(taps, layout, tangents, weights, disparity, confidence);
                None
            }
            Method::Poisson(params) => {
                let weights = self.weight_maps(Weighting::Frustum);
                let report = blend::poisson_blend_with_prior(
                    taps, layout, tangents, weights, params, prior, disparity, confidence,
                )?;
                Some(report)
            }
        };
        Ok(BlendReport {
            method: *method,
            poisson,
        })
    }

    /// Bytes held by the maps built so far.
    pub fn memory_bytes(&self) -> usize {
        self.tangent_taps.get().map_or(0, TangentTaps::memory_bytes)
            + self.erp_taps.get().map_or(0, ErpTaps::memory_bytes)
            + self
                .weight_maps
                .iter()
                .filter_map(OnceLock::get)
                .map(WeightMaps::memory_bytes)
                .sum::<usize>()
    }
}

fn weight_slot(kind: Weighting) -> usize {
    Weighting::ALL
        .iter()
        .position(|(k, _)| *k == kind)
        .unwrap_or_default()
}

/// The value in `cell`, built by `build` first if there is none, without holding any lock while
/// `build` runs (see the module documentation).
fn get_or_build<T>(cell: &OnceLock<T>, build: impl FnOnce() -> T) -> &T {
    if let Some(value) = cell.get() {
        return value;
    }
    let built = build();
    // Another thread may have stored its copy meanwhile: keep the first.
    drop(cell.set(built));
    cell.get().unwrap_or_else(|| unreachable!("set above"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::mpsc;
    use std::time::Duration;

    /// Regression test of the deadlock found under concurrent first calls: several threads,
    /// each entering the same pool with work that needs maps of a fresh plan, the maps built
    /// with parallel work. With the maps built inside the pool behind a lock the threads ended
    /// in a futex wait; with `prepare` outside the pool they finish. A watchdog fails the test
    /// instead of hanging.
    #[test]
    fn concurrent_first_calls_on_fresh_plans_finish() {
        let pool = Arc::new(
            rayon::ThreadPoolBuilder::new()
                .num_threads(2)
                .build()
                .expect("pool"),
        );
        let (done, finished) = mpsc::channel();
        let worker = std::thread::spawn(move || {
            for trial in 0..6 {
                let plan = Arc::new(Plan::new(
                    Layout::icosahedron(128 + 32 * trial, 0.3, None).expect("layout"),
                ));
                let threads: Vec<_> = [
                    vec![Need::TangentTaps],
                    vec![Need::ErpTaps, Need::WeightMaps(Weighting::Frustum)],
                    vec![Need::ErpTaps, Need::WeightMaps(Weighting::Frustum)],
                    vec![Need::Overlaps(0.01, 0.0), Need::ErpTaps],
                ]
                .into_iter()
                .map(|needs| {
                    let (plan, pool) = (plan.clone(), pool.clone());
                    std::thread::spawn(move || {
                        plan.prepare(&needs, |build| pool.install(build));
                        pool.install(|| {
                            rayon::join(
                                || plan.erp_taps().len(),
                                || plan.tangent_taps().memory_bytes(),
                            )
                        })
                    })
                })
                .collect();
                let sizes: Vec<_> = threads
                    .into_iter()
                    .map(|t| t.join().expect("thread"))
                    .collect();
                assert!(sizes.windows(2).all(|w| w[0] == w[1]));
            }
            done.send(()).expect("send");
        });
        finished
            .recv_timeout(Duration::from_secs(300))
            .expect("concurrent first calls deadlocked");
        worker.join().expect("worker");
    }

    #[test]
    fn prepare_builds_what_is_needed_and_only_that() {
        let plan = Plan::new(Layout::icosahedron(128, 0.3, None).expect("layout"));
        assert_eq!(plan.memory_bytes(), 0);
        plan.prepare(&Plan::blend_needs(&Method::Mean), |build| build());
        assert!(plan.is_built(Need::ErpTaps));
        assert!(!plan.is_built(Need::TangentTaps));
        assert!(!plan.is_built(Need::WeightMaps(Weighting::Frustum)));
        plan.prepare(&Plan::blend_needs(&Method::Frustum), |build| build());
        assert!(plan.is_built(Need::WeightMaps(Weighting::Frustum)));
    }
}
