//! Per-(layout, ERP size) sampling maps, built on first use and shared by every later image.

use crate::align::Overlaps;
use crate::blend::{weight_maps, Weighting};
use crate::layout::Layout;
use crate::resample::{ErpTaps, TangentTaps, TapWeights};
use std::sync::{Arc, Mutex, OnceLock};

/// (sample fraction, pole cap) as bit patterns: the options overlap samples depend on.
type OverlapKey = (u64, u64);

/// Everything that depends only on the layout (and so on the ERP size), not on the image.
///
/// Each map is built the first time an operation needs it (in parallel, on the calling thread
/// pool) and then reused, so a batch of same-size panoramas pays for it once.
#[derive(Debug)]
pub struct Plan {
    layout: Layout,
    tangent_taps: OnceLock<TangentTaps>,
    erp_taps: OnceLock<ErpTaps>,
    /// Overlap samples per (sample fraction, pole cap) — a handful of option sets at most.
    overlaps: Mutex<Vec<(OverlapKey, Arc<Overlaps>)>>,
    /// Weights at every ERP tap, per [`Weighting`] (the weight maps themselves are not kept:
    /// the blends only ever read them at the taps).
    tap_weights: [OnceLock<TapWeights>; 4],
}

impl Plan {
    /// A plan for `layout`; no map is built yet.
    pub fn new(layout: Layout) -> Self {
        Self {
            layout,
            tangent_taps: OnceLock::new(),
            erp_taps: OnceLock::new(),
            overlaps: Mutex::new(Vec::new()),
            tap_weights: Default::default(),
        }
    }

    /// The layout this plan serves.
    pub fn layout(&self) -> &Layout {
        &self.layout
    }

    /// Where each tangent pixel samples the ERP image (built on first call).
    pub fn tangent_taps(&self) -> &TangentTaps {
        self.tangent_taps
            .get_or_init(|| TangentTaps::build(&self.layout))
    }

    /// Which tangents, and where, each ERP pixel sees (built on first call).
    pub fn erp_taps(&self) -> &ErpTaps {
        self.erp_taps.get_or_init(|| ErpTaps::build(&self.layout))
    }

    /// Overlap samples for alignment with these options (built on first call).
    pub fn overlaps(&self, fraction: f64, pole_cap_deg: f64) -> Arc<Overlaps> {
        let key = (fraction.to_bits(), pole_cap_deg.to_bits());
        // A poisoned lock only means another thread panicked mid-build; the cache stays valid.
        let mut cache = self.overlaps.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((_, found)) = cache.iter().find(|(k, _)| *k == key) {
            return found.clone();
        }
        let built = Arc::new(Overlaps::build(&self.layout, fraction, pole_cap_deg));
        cache.push((key, built.clone()));
        built
    }

    /// Blending weights of `kind` at every ERP tap (built on first call, with the ERP taps).
    pub fn tap_weights(&self, kind: Weighting) -> &TapWeights {
        let slot = match kind {
            Weighting::Nearest => 0,
            Weighting::Mean => 1,
            Weighting::Radial => 2,
            Weighting::Frustum => 3,
        };
        self.tap_weights[slot]
            .get_or_init(|| self.erp_taps().weights_of(&weight_maps(&self.layout, kind)))
    }

    /// Bytes held by the maps built so far.
    pub fn memory_bytes(&self) -> usize {
        self.tangent_taps.get().map_or(0, TangentTaps::memory_bytes)
            + self.erp_taps.get().map_or(0, ErpTaps::memory_bytes)
            + self
                .tap_weights
                .iter()
                .filter_map(OnceLock::get)
                .map(TapWeights::memory_bytes)
                .sum::<usize>()
    }
}
