//! The global prior term of the alignment (docs/method.md, "Global prior").
//!
//! A prior is an ERP map of spherical disparity (any resolution, NaN = unknown, optionally with a
//! per-pixel confidence in [0, 1]), absolute or known only up to its own affine map. It is read
//! at deterministic sample pixels of every tangent and pulls the tangent's aligned disparity
//! s·D + o·f there towards α·P + β, with (α, β) one extra node of unknowns solved jointly with
//! the fields. Each prior sample has its own Cauchy IRLS weight (times its confidence), so prior
//! regions that all tangents contradict lose their pull.

use super::{splitmix64, MapValues, SAMPLE_BUDGET_PIXELS};
use crate::error::{CoreError, Result};
use crate::layout::Layout;
use crate::sphere::direction_to_pixel;
use rayon::prelude::*;
use std::sync::{Arc, Mutex, PoisonError};

/// A prior map over the whole sphere in spherical disparity: relative (`absolute = false`:
/// only α·P + β is compared) or absolute (the aligned result is expressed in its units).
#[derive(Debug, Clone)]
pub struct Prior {
    /// ERP values, row-major `height`×`width` (NaN = unknown).
    pub values: Vec<f32>,
    /// Per-pixel confidence in [0, 1] (same shape), or None for all 1.
    pub confidence: Option<Vec<f32>>,
    /// ERP rows.
    pub height: usize,
    /// ERP columns (2·height).
    pub width: usize,
    /// Whether the prior's units are the result's (disparity in 1/m): the alignment's result is
    /// then mapped into them.
    pub absolute: bool,
}

impl Prior {
    /// Check shapes and values.
    ///
    /// # Errors
    /// [`CoreError::ShapeMismatch`] for a wrong length or aspect, [`CoreError::Degenerate`] for a
    /// prior without a finite value or a confidence outside [0, 1].
    pub fn validate(&self) -> Result<()> {
        if self.height < 2 || self.width != 2 * self.height {
            return Err(CoreError::ShapeMismatch {
                what: "prior (an ERP map: width = 2 x height, at least 2 x 4)",
                expected: vec![self.height.max(2), 2 * self.height.max(2)],
                actual: vec![self.height, self.width],
            });
        }
        let n = self.height * self.width;
        if self.values.len() != n {
            return Err(CoreError::ShapeMismatch {
                what: "prior values",
                expected: vec![n],
                actual: vec![self.values.len()],
            });
        }
        if !self.values.iter().any(|v| v.is_finite()) {
            return Err(CoreError::Degenerate(
                "the prior has no finite value (all NaN or infinite)".into(),
            ));
        }
        if let Some(c) = &self.confidence {
            if c.len() != n {
                return Err(CoreError::ShapeMismatch {
                    what: "prior confidence",
                    expected: vec![self.height, self.width],
                    actual: vec![c.len()],
                });
            }
            if c.iter().any(|v| !(0.0..=1.0).contains(v)) {
                return Err(CoreError::Degenerate(
                    "prior confidence must lie in [0, 1] (NaN not allowed)".into(),
                ));
            }
        }
        Ok(())
    }

    /// Bilinear value and confidence at continuous ERP position (col, row): longitude wraps,
    /// rows clamp; None when a contributing value is not finite or the confidence is 0.
    fn sample(&self, col: f64, row: f64) -> Option<(f64, f64)> {
        let (h, w) = (self.height, self.width);
        let row = row.clamp(0.0, (h - 1) as f64);
        let r0 = (row as usize).min(h - 2);
        let fy = row - r0 as f64;
        let col = col.rem_euclid(w as f64);
        let c0 = (col as usize).min(w - 1);
        let fx = col - c0 as f64;
        let c1 = (c0 + 1) % w;
        let idx = [
            r0 * w + c0,
            r0 * w + c1,
            (r0 + 1) * w + c0,
            (r0 + 1) * w + c1,
        ];
        let wts = [
            (1.0 - fx) * (1.0 - fy),
            fx * (1.0 - fy),
            (1.0 - fx) * fy,
            fx * fy,
        ];
        let mut value = 0.0;
        let mut conf = 0.0;
        for (&i, &wt) in idx.iter().zip(&wts) {
            let v = self.values[i];
            if !v.is_finite() {
                return None;
            }
            value += wt * f64::from(v);
            conf += wt * self.confidence.as_ref().map_or(1.0, |c| f64::from(c[i]));
        }
        (conf > 0.0).then_some((value, conf))
    }
}

/// The prior read at deterministic pixels of every tangent, with the tangents' values there
/// (low-passed over the frequency split's radius, before any alignment step).
#[derive(Debug, Clone, Default)]
pub struct PriorSamples {
    /// Tangent of each sample.
    pub(super) tangent: Vec<u16>,
    /// Pixel index y·w + x in the tangent.
    pub(super) pixel: Vec<u32>,
    /// The prior there, standardised: (P − median)/spread over the samples.
    pub(super) value: Vec<f64>,
    /// The prior's confidence there (bilinear).
    pub(super) confidence: Vec<f64>,
    /// The tangent's raw value there, averaged over the low-pass window.
    pub(super) raw: Vec<f32>,
    /// (median, spread) that standardised the prior values.
    pub(super) stats: (f64, f64),
    /// Whether the prior is absolute.
    pub(super) absolute: bool,
    /// The other tangents that see each sample's direction: sample k's are entries
    /// `view_start[k]..view_start[k + 1]` of (tangent, x, y).
    pub(super) view_start: Vec<u32>,
    pub(super) view_tangent: Vec<u16>,
    pub(super) view_xy: Vec<[f32; 2]>,
    /// The raw values of the four pixels around each view's position (kept so that a level
    /// reads them through its transform without visiting the maps again: random reads over
    /// all tangents were a tenth of a stitch with a prior).
    pub(super) view_raw: Vec<[f32; 4]>,
    /// Cell of each sample's direction in a [`TRUST_ROWS`] × 2·[`TRUST_ROWS`] ERP grid.
    pub(super) cell: Vec<u32>,
    /// Pixels drawn, before those without a finite tangent value or prior were left out.
    pub(super) drawn: usize,
}

/// Index in its tangent (y·w + x) of the top-left of the four pixels a view at `xy` reads.
pub(super) fn view_corner(xy: [f32; 2], w: usize, h: usize) -> usize {
    let x0 = (xy[0] as usize).min(w - 2);
    let y0 = (xy[1] as usize).min(h - 2);
    y0 * w + x0
}

/// Rows of the ERP grid over which the prior's trust, judged where tangents overlap, is spread
/// to where one tangent alone sees the sphere (6° cells).
pub const TRUST_ROWS: usize = 30;

/// One tangent's samples: (tangent, pixel, prior value, confidence, raw window mean).
type Part = (
    Vec<(u16, u32, f64, f64, f32, u32)>,
    Vec<(u32, u16, [f32; 2], [f32; 4])>,
);

/// Salt of the prior samples' hash, so they are not the overlap samples' pixels.
const PRIOR_SALT: u64 = 0x5052_494F_5200_0000;

/// Taps per side of the low-pass window (2·K + 1 taps, spaced to span its radius).
const WINDOW_TAPS: usize = 2;

impl PriorSamples {
    /// Read `prior` at a `fraction` of the pixels of every tangent of `layout` (the overlap
    /// samples' budget rule: large tangents keep that fraction of [`SAMPLE_BUDGET_PIXELS`]), with
    /// the raw tangent values of `maps` averaged over a window of `radius_deg` degrees.
    ///
    /// # Errors
    /// [`CoreError::Degenerate`] when no tangent pixel sees a finite prior value.
    pub fn build(
        layout: &Layout,
        maps: &[f32],
        prior: &Prior,
        fraction: f64,
        radius_deg: f64,
    ) -> Result<Self> {
        prior.validate()?;
        let (h, w) = layout.tangent_shape();
        let budget = (SAMPLE_BUDGET_PIXELS as f64 / (h * w) as f64).min(1.0);
        let threshold = (fraction.clamp(0.0, 1.0) * budget * u64::MAX as f64) as u64;
        let chosen = sample_pixels(layout.cameras.len(), h * w, threshold);
        let parts: Vec<Part> = (0..layout.cameras.len())
            .into_par_iter()
            .map(|t| {
                let cam = &layout.cameras[t];
                // Pixels per degree at the tangent's centre; the window's taps span the radius.
                let radius_px = radius_deg.to_radians() * cam.fx;
                let stride = ((radius_px / WINDOW_TAPS as f64).round() as usize).max(1);
                let reach = if radius_px >= 0.5 { WINDOW_TAPS } else { 0 };
                let map = &maps[t * h * w..(t + 1) * h * w];
                let mut out = Vec::new();
                let mut views = Vec::new();
                for &p in &chosen[t] {
                    let p = p as usize;
                    if !map[p].is_finite() {
                        continue;
                    }
                    let (x, y) = (p % w, p / w);
                    let d = cam.pixel_direction(x as f64, y as f64);
                    let (col, row) = direction_to_pixel(&d, prior.height, prior.width);
                    let Some((value, conf)) = prior.sample(col, row) else {
                        continue;
                    };
                    let Some(raw) = window_mean(map, w, h, x, y, reach, stride) else {
                        continue;
                    };
                    // Where the other tangents see this direction (their consensus decides
                    // whether the prior is wrong here).
                    for (b, cam_b) in layout.cameras.iter().enumerate() {
                        if b == t {
                            continue;
                        }
                        if let Some((xb, yb)) = cam_b.project(&d) {
                            if cam_b.contains(xb, yb) {
                                let xy = [
                                    xb.clamp(0.0, (w - 1) as f64) as f32,
                                    yb.clamp(0.0, (h - 1) as f64) as f32,
                                ];
                                let base = b * h * w + view_corner(xy, w, h);
                                let raw = [base, base + 1, base + w, base + w + 1].map(|i| maps[i]);
                                views.push((out.len() as u32, b as u16, xy, raw));
                            }
                        }
                    }
                    let (cc, cr) = direction_to_pixel(&d, TRUST_ROWS, 2 * TRUST_ROWS);
                    let cell_row = (cr.round().max(0.0) as usize).min(TRUST_ROWS - 1);
                    let cell_col = (cc.round().rem_euclid(2.0 * TRUST_ROWS as f64)) as usize
                        % (2 * TRUST_ROWS);
                    let cell = (cell_row * 2 * TRUST_ROWS + cell_col) as u32;
                    out.push((t as u16, p as u32, value, conf, raw, cell));
                }
                (out, views)
            })
            .collect();
        let mut samples = Self {
            absolute: prior.absolute,
            drawn: chosen.iter().map(Vec::len).sum(),
            ..Self::default()
        };
        samples.view_start.push(0);
        for (part, views) in parts {
            let mut views = views.into_iter().peekable();
            for (i, (t, p, v, c, raw, cell)) in part.into_iter().enumerate() {
                while let Some(&(k, b, xy, raw)) = views.peek() {
                    if k != i as u32 {
                        break;
                    }
                    samples.view_tangent.push(b);
                    samples.view_xy.push(xy);
                    samples.view_raw.push(raw);
                    views.next();
                }
                samples.view_start.push(samples.view_tangent.len() as u32);

                samples.tangent.push(t);
                samples.pixel.push(p);
                samples.value.push(v);
                samples.confidence.push(c);
                samples.raw.push(raw);
                samples.cell.push(cell);
            }
        }
        if samples.tangent.is_empty() {
            return Err(CoreError::Degenerate(
                "no tangent pixel sees a finite prior value".into(),
            ));
        }
        let values: Vec<f32> = samples.value.iter().map(|&v| v as f32).collect();
        let (median, spread) = super::median_and_spread(&values).unwrap_or((0.0, 1.0));
        let spread = if spread > 0.0 { spread } else { 1.0 };
        for v in &mut samples.value {
            *v = (*v - median) / spread;
        }
        samples.stats = (median, spread);
        Ok(samples)
    }

    /// Number of samples.
    #[must_use]
    pub fn len(&self) -> usize {
        self.tangent.len()
    }

    /// Whether there are none.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.tangent.is_empty()
    }

    /// The tangent's value at sample k through `maps` (its raw window mean taken through the
    /// alignment steps so far), given the tangent shape.
    pub(super) fn tangent_value<M: MapValues + ?Sized>(
        &self,
        k: usize,
        maps: &M,
        tangent_pixels: usize,
    ) -> f32 {
        let index = self.tangent[k] as usize * tangent_pixels + self.pixel[k] as usize;
        maps.through(index, self.raw[k])
    }
}

/// The tangents' relative spread (median over the prior samples two or more tangents see, after
/// the schedule's first level) at or below which their own consensus is trusted over the prior in
/// full at low frequencies, and at or above which not at all (docs/method.md, "The tangents'
/// own low frequencies"). Synthetic rooms: tangents with no smooth error 0.002–0.003, with a
/// ±3 % one 0.004, ±6 % 0.006–0.007, ±10 % 0.009–0.011, with content errors 0.015–0.019; the
/// shared real networks 0.05–0.16.
pub const TRUSTED_SPREAD: f64 = 0.004;
/// See [`TRUSTED_SPREAD`].
pub const UNTRUSTED_SPREAD: f64 = 0.012;
/// The share of the prior sample pixels drawn whose tangent value and prior must be known for
/// the fusion to run (a masked or partial panorama, or a prior with holes, is left as it is).
const FUSION_MIN_COVERAGE: f64 = 0.9;

/// The tangents' relative spread (the median over the samples two or more tangents see; None
/// without such samples) and whether their overlaps are deep: most samples are seen by
/// [`EVIDENCE_MIN_VIEWS`] tangents or more. `consensus`: per sample (mean, relative spread,
/// number of tangents), None where its own tangent has no value.
fn spread_and_depth(consensus: &[Option<(f64, f64, usize)>]) -> Option<(f64, bool)> {
    let spreads: Vec<f64> = consensus
        .iter()
        .flatten()
        .filter(|c| c.2 >= 2)
        .map(|c| c.1)
        .collect();
    if spreads.is_empty() {
        return None;
    }
    let mut views: Vec<usize> = consensus.iter().flatten().map(|c| c.2).collect();
    let mid = views.len() / 2;
    let deep = *views.select_nth_unstable(mid).1 >= EVIDENCE_MIN_VIEWS;
    Some((super::median_abs(&spreads), deep)) // spreads are ≥ 0
}

/// The prior moved towards the tangents' own consensus at low frequencies ([`PriorSamples::fused`]).
#[derive(Debug, Clone, Default)]
pub(super) struct Fusion {
    /// The prior samples with their fused values; None when the share is 0 (the prior as it is).
    pub(super) samples: Option<PriorSamples>,
    /// The tangents' relative spread that decided the share.
    pub(super) spread: f64,
    /// The share γ of the tangents' low-frequency disagreement with the prior that moved it.
    pub(super) share: f64,
    /// The share of the prior samples the consensus outvoted (their confidence set to 0).
    pub(super) outvoted: f64,
    /// The prior's disagreement with the consensus at the sphere's largest scales (RMS of the
    /// relative gap's spherical harmonics of degree ≤ 2, [`low_order_gap`]; 0: not measured).
    pub(super) low_order_gap: f64,
    /// The share of that disagreement that moved the prior ([`low_order_share`]).
    pub(super) low_order_share: f64,
}

/// The tangents' values at a prior sample's direction (its own tangent's, then its views'):
/// their mean, standard deviation and number.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Consensus {
    pub(super) mean: f64,
    pub(super) std: f64,
    pub(super) seen_by: usize,
}

impl Consensus {
    /// Of `values` (at least one).
    pub(super) fn of(values: impl Iterator<Item = f64> + Clone) -> Self {
        let n = values.clone().count();
        let mean = values.clone().sum::<f64>() / n as f64;
        let var = values.map(|v| (v - mean).powi(2)).sum::<f64>() / n as f64;
        Self {
            mean,
            std: var.sqrt(),
            seen_by: n,
        }
    }
}

impl PriorSamples {
    /// The value at view v (of another tangent than the sample's) through `maps`: the bilinear
    /// mean of the four raw pixels kept at the build, read as `maps` reads them; None when one is
    /// not finite.
    pub(super) fn view_value<M: MapValues + ?Sized>(
        &self,
        v: usize,
        maps: &M,
        w: usize,
        h: usize,
    ) -> Option<f64> {
        let [xb, yb] = self.view_xy[v].map(f64::from);
        let at = view_corner(self.view_xy[v], w, h);
        let (x0, y0) = (at % w, at / w);
        let base = self.view_tangent[v] as usize * h * w + at;
        let step = [0, 1, w, w + 1];
        let corners: [f64; 4] =
            std::array::from_fn(|c| f64::from(maps.through(base + step[c], self.view_raw[v][c])));
        if corners.iter().any(|v| !v.is_finite()) {
            return None;
        }
        Some(
            super::bilinear_weights(xb - x0 as f64, yb - y0 as f64)
                .iter()
                .zip(&corners)
                .map(|(w, v)| w * v)
                .sum(),
        )
    }

    /// The prior moved towards the tangents' `consensus` at its samples (indexed as they are,
    /// None where the sample's own tangent has no value; [`super::Problem::prior_consensus`]
    /// reads it off the problem of the level the prior joins, after the schedule's first level,
    /// which is solved without the prior), where the tangents agree with each other well enough
    /// to be trusted: a deformation shared by all tangents is invisible to their overlaps, so
    /// without this the result takes the prior's own smooth error in full, however good the
    /// tangents (exact ones: 0.004 → 0.009 AbsRel at 2K).
    ///
    /// The tangents' relative spread at a sample is std/|c|, c their mean (in the units
    /// `frame` = (spread, median) restores). The median spread s over the samples seen twice or
    /// more sets the share γ = (UNTRUSTED − s)/(UNTRUSTED − TRUSTED) in [0, 1]. The disagreement
    /// c − (α·P + β), with (α, β) fitted as the prior joins ([`super::symmetric_line`]), is
    /// low-passed over 6° trust cells and their 8 neighbours (≈ 18°; weighted by confidence and
    /// by the Cauchy weight of the gap, only where two tangents or more see the sample), its
    /// affine part in P removed with the same weights (the fusion changes the prior's shape, not
    /// its units), and γ of it moves each sample's value. With deep overlaps γ rises to what the
    /// evidence supports when that is more ([`evidence_share`], from `variance`, called only
    /// then: per sample, the consensus's low-frequency variance,
    /// [`super::Problem::consensus_variance`]). With deep overlaps and a spread up to
    /// [`OUTVOTE_MAX_SPREAD`], whatever the share, the samples far outside that variance lose
    /// their confidence ([`consensus_outvotes`]). None
    /// when no sample is seen twice, fewer than [`FUSION_MIN_COVERAGE`] of the drawn pixels are
    /// samples, or, with a share to give, the fit is degenerate.
    pub(super) fn fused(
        &self,
        consensus: &[Option<Consensus>],
        variance: impl FnOnce() -> Option<Vec<Option<f64>>>,
        frame: (f64, f64),
    ) -> Option<Fusion> {
        debug_assert_eq!(consensus.len(), self.len());
        let consensus: Vec<Option<(f64, f64, usize)>> = consensus
            .iter()
            .map(|c| {
                c.map(|c| {
                    let level = (c.mean * frame.0 + frame.1).abs().max(f64::MIN_POSITIVE);
                    (c.mean, c.std * frame.0.abs() / level, c.seen_by)
                })
            })
            .collect();
        // The first level determines the tangents' common shape only where they overlap all
        // around the sphere: a partial panorama (a masked half) left groups of tangents in
        // gauges of their own, which agree locally and mislead the fusion.
        let finite = consensus.iter().filter(|c| c.is_some()).count();
        if (finite as f64) < FUSION_MIN_COVERAGE * self.drawn as f64 {
            return None;
        }
        let (spread, deep) = spread_and_depth(&consensus)?;
        let share =
            ((UNTRUSTED_SPREAD - spread) / (UNTRUSTED_SPREAD - TRUSTED_SPREAD)).clamp(0.0, 1.0);
        let outvoting = deep && spread <= OUTVOTE_MAX_SPREAD;
        // The prior as it is: nothing to fuse, and no consensus to outvote by (below).
        let unmoved = Fusion {
            spread,
            ..Fusion::default()
        };
        if share <= 0.0 && !outvoting {
            return Some(unmoved);
        }
        let unmoved = (share <= 0.0).then_some(unmoved);
        let seen: Vec<usize> = (0..self.len())
            .filter(|&k| consensus[k].is_some())
            .collect();
        let p: Vec<f64> = seen.iter().map(|&k| self.value[k]).collect();
        let c: Vec<f64> = seen
            .iter()
            .filter_map(|&k| consensus[k].map(|c| c.0))
            .collect();
        let conf: Vec<f64> = seen.iter().map(|&k| self.confidence[k]).collect();
        let (alpha, beta) = match super::symmetric_line(&p, &c, &conf) {
            Some(line) if line.0.abs() > f64::MIN_POSITIVE => line,
            _ => return unmoved,
        };
        let gap: Vec<f64> = c
            .iter()
            .zip(&p)
            .map(|(c, p)| c - (alpha * p + beta))
            .collect();
        let shared: Vec<bool> = seen
            .iter()
            .map(|&k| consensus[k].is_some_and(|c| c.2 >= 2))
            .collect();
        let cells: Vec<u32> = seen.iter().map(|&k| self.cell[k]).collect();
        let (centre, sigma, shift) = low_passed_gap(&gap, &p, &conf, &cells, &shared);
        // The consensus variance is read only with deep overlaps: the paper's layout never pays
        // for it. Where most samples are seen by 2-4 tangents the first level has made those
        // few agree, and their spread says too little of their error.
        let variance = deep.then(variance).flatten();
        let var_c = |j: usize| {
            variance
                .as_ref()
                .and_then(|v| v[seen[j]])
                .filter(|_| shared[j])
        };
        // Where the prior's low frequencies stray from the tangents' consensus by more than the
        // consensus's own uncertainty explains, the prior is the worse of the two: the share
        // rises towards the inverse-variance weight var_p/(var_p + var_c). A prior with a
        // smooth error as large as the tangents' then no longer makes the result much worse
        // than no prior (docs/method.md, "The prior's own quality").
        let share = if share > 0.0 && variance.is_some() {
            // Only where the sample's own gap is an inlier: inside a regional error the
            // low-passed gap is the region's, which the judgement outvotes anyway.
            share.max(evidence_share(&shift, |j| {
                var_c(j).filter(|_| (gap[j] - centre).abs() <= EVIDENCE_INLIER * sigma)
            }))
        } else {
            share
        };
        // A prior sample far outside the consensus's uncertainty, at low frequency and on its
        // own, and by more than the prior's plausible smooth error, is wrong there: it is
        // outvoted before it can pull (docs/method.md, "Outvoted by the consensus").
        let level =
            |j: usize| (c[j] * frame.0 + frame.1).abs() / frame.0.abs().max(f64::MIN_POSITIVE);
        let voting = |j: usize| var_c(j).filter(|_| outvoting);
        let outvoted = consensus_outvotes(&gap, centre, &shift, voting, level);
        let count = outvoted.iter().filter(|&&o| o).count();
        // Where the fusion gives nothing (the tangents spread too widely to correct the prior's
        // shape sample by sample), their consensus over the whole sphere can still correct its
        // largest scales: a prior bent as a whole (docs/method.md, "The sphere's largest scales").
        // Not beside a regional error large enough to be outvoted in bulk: its terms of degree 1
        // and 2 look like a bend.
        let low = (outvoting && share <= 0.0 && !outvoted_in_bulk(&gap, centre, &outvoted))
            .then(|| {
                let views = |j: usize| consensus[seen[j]].map_or(1, |c| c.2);
                let weights = low_order_weights(&shared, &outvoted, &conf, &cells, views);
                low_order_gap(&gap, &shift, level, &weights, &cells)
            })
            .flatten()
            .unwrap_or_default();
        // Nothing moved (the fusion's share 0, nothing outvoted, no bend): the prior as it is.
        let moved = share > 0.0 || count > 0 || low.share > 0.0;
        let samples = moved.then(|| {
            let mut samples = self.clone();
            for (j, (&k, s)) in seen.iter().zip(&shift).enumerate() {
                // The fitted prior's disparity times exp(γ·field) at the largest scales.
                let fitted = alpha * p[j] + beta + frame.1 / frame.0;
                let bend = low.field.get(j).map_or(0.0, |f| (low.share * f).exp_m1());
                samples.value[k] += (share * s + fitted * bend) / alpha;
                if outvoted[j] {
                    samples.confidence[k] = 0.0;
                }
            }
            samples
        });
        Some(Fusion {
            samples,
            spread,
            share,
            outvoted: count as f64 / seen.len() as f64,
            low_order_gap: low.gap,
            low_order_share: low.share,
        })
    }
}

/// The prior's disagreement `gap` with the tangents' consensus at low frequency: its centre
/// (median over the `shared` samples, those two tangents or more see), its robust scale there,
/// and per sample its mean over the sample's 6° trust cell (`cells`) and the 8 around, with
/// the affine part in the prior's values `p` removed. Only where tangents overlap is their
/// consensus theirs (one tangent alone is held by nothing but the prior), and a regional error
/// of the prior (a jump in the gap, which the judgement outvotes) must not spread into the
/// low-pass: the means weigh the confidence `conf` times the Cauchy weight of the gap at its
/// own robust scale. The line is fitted with the same weights: a regional error must not tilt
/// it (with confidence weights alone, a cap 30 % wrong on a fifth of the sphere moved the whole
/// fused prior).
fn low_passed_gap(
    gap: &[f64],
    p: &[f64],
    conf: &[f64],
    cells: &[u32],
    shared: &[bool],
) -> (f64, f64, Vec<f64>) {
    let overlapped: Vec<f64> = (0..gap.len())
        .filter(|&j| shared[j])
        .map(|j| gap[j])
        .collect();
    let (centre, sigma) = centre_and_scale(&overlapped);
    let sigma = sigma.max(super::MIN_PRIOR_SCALE);
    let weights: Vec<f64> = (0..gap.len())
        .map(|j| {
            if shared[j] {
                conf[j] * super::Loss::Cauchy.weight(gap[j] - centre, sigma)
            } else {
                0.0
            }
        })
        .collect();
    let smooth = super::CellMeans::weighted(cells, gap, &weights);
    let mut shift: Vec<f64> = cells
        .iter()
        .map(|&cell| smooth.around(cell as usize).unwrap_or(0.0))
        .collect();
    remove_line(p, &mut shift, &weights);
    (centre, sigma, shift)
}

/// The median of `values` (at least one) and the robust scale of their deviations from it.
fn centre_and_scale(values: &[f64]) -> (f64, f64) {
    let mut sorted = values.to_vec();
    let mid = sorted.len() / 2;
    let (_, &mut centre, _) = sorted.select_nth_unstable_by(mid, f64::total_cmp);
    let centred: Vec<f64> = values.iter().map(|v| v - centre).collect();
    (centre, super::robust_scale(&centred))
}

/// Which samples the tangents' consensus outvotes: those whose own `gap` (from its `centre`) and
/// low-passed gap `shift`, of one sign, both exceed [`OUTVOTE_STANDARD_ERRORS`] of the
/// consensus's standard error √`var_c(j)` (None: not measured, never outvoted), the low-passed
/// one also [`OUTVOTE_RELATIVE_GAP`] of the disparity `level(j)` (in the gap's units). A smooth
/// deformation is not caught by the judgement's robust scale when it covers much of the sphere,
/// and a regional error's border is held by its neighbours' trust; against the consensus's own
/// uncertainty both stand out.
fn consensus_outvotes(
    gap: &[f64],
    centre: f64,
    shift: &[f64],
    var_c: impl Fn(usize) -> Option<f64>,
    level: impl Fn(usize) -> f64,
) -> Vec<bool> {
    (0..gap.len())
        .map(|j| {
            var_c(j).is_some_and(|var_c| {
                let bound = OUTVOTE_STANDARD_ERRORS * var_c.sqrt();
                let own = gap[j] - centre;
                own * shift[j] > 0.0
                    && own.abs() > bound
                    && shift[j].abs() > bound.max(OUTVOTE_RELATIVE_GAP * level(j))
            })
        })
        .collect()
}

/// The prior's disagreement with the tangents' consensus at the sphere's largest scales
/// ([`low_order_gap`]).
#[derive(Debug, Clone, Default)]
struct LowOrder {
    /// The fitted field at every sample (empty when not fitted).
    field: Vec<f64>,
    /// Its RMS over the fitted samples (0: not measured).
    gap: f64,
    /// The share of it that moves the prior ([`low_order_share`]).
    share: f64,
}

/// The weights of the samples in [`low_order_gap`]'s fit: their confidence over the number of
/// tangents that see them (`views(j)`: the samples' density grows with the overlaps), and 0 for
/// a sample only one tangent sees (held by nothing but the prior), one the consensus outvoted,
/// or one in a trust cell whose neighbourhood (the cell and the 8 around) has more than
/// [`NEAR_OUTVOTED`] of its samples outvoted: a regional error's rest.
fn low_order_weights(
    shared: &[bool],
    outvoted: &[bool],
    conf: &[f64],
    cells: &[u32],
    views: impl Fn(usize) -> usize,
) -> Vec<f64> {
    let flags: Vec<f64> = outvoted.iter().map(|&o| f64::from(u8::from(o))).collect();
    let near = super::CellMeans::weighted(cells, &flags, conf);
    (0..conf.len())
        .map(|j| {
            let clear = near.around(cells[j] as usize).unwrap_or(0.0) <= NEAR_OUTVOTED;
            if shared[j] && !outvoted[j] && clear {
                conf[j] / views(j).max(1) as f64
            } else {
                0.0
            }
        })
        .collect()
}

/// The prior's disagreement with the tangents' consensus at the sphere's largest scales: the
/// relative gap `gap[j]/level(j)` fitted by weighted least squares with the real spherical
/// harmonics of degree ≤ 2 at the directions of the samples' trust cells `cells`, over the
/// samples with a `weight` whose low-passed relative gap `shift[j]/level(j)` and own relative
/// gap both lie within [`EVIDENCE_INLIER`] robust scales of their medians. A regional error of
/// the prior has large terms of degree 1 and 2 too, which the fit would take for a bend and
/// spread over the sphere; what of it the outvote left stands out of those distributions, while
/// a smooth bend spreads through them. The field is returned at every sample, its weighted mean
/// over the fitted samples removed (the prior's units are not its business), with its RMS there
/// and the share [`low_order_share`] gives it; None with fewer fitted samples than 10 per term
/// or a singular fit.
fn low_order_gap(
    gap: &[f64],
    shift: &[f64],
    level: impl Fn(usize) -> f64,
    weight: &[f64],
    cells: &[u32],
) -> Option<LowOrder> {
    let candidates: Vec<usize> = (0..gap.len())
        .filter(|&j| weight[j] > 0.0 && level(j) > 0.0)
        .collect();
    if candidates.is_empty() {
        return None;
    }
    // Within EVIDENCE_INLIER robust scales of its median, both low-passed and the sample's own.
    let inlier = |of: &dyn Fn(usize) -> f64| -> Vec<bool> {
        let values: Vec<f64> = candidates.iter().map(|&j| of(j)).collect();
        let (centre, sigma) = centre_and_scale(&values);
        let bound = EVIDENCE_INLIER * sigma;
        values.iter().map(|v| (v - centre).abs() <= bound).collect()
    };
    let low = inlier(&|j| shift[j] / level(j));
    let own = inlier(&|j| gap[j] / level(j));
    let fitted: Vec<usize> = (0..candidates.len())
        .filter(|&i| low[i] && own[i])
        .map(|i| candidates[i])
        .collect();
    if fitted.len() < 10 * LOW_ORDER_TERMS {
        return None;
    }
    let basis = |j: usize| low_order_basis(cell_direction(cells[j]));
    let mut normal = nalgebra::SMatrix::<f64, LOW_ORDER_TERMS, LOW_ORDER_TERMS>::zeros();
    let mut rhs = nalgebra::SVector::<f64, LOW_ORDER_TERMS>::zeros();
    for &j in &fitted {
        let b = nalgebra::SVector::<f64, LOW_ORDER_TERMS>::from(basis(j));
        normal += weight[j] * b * b.transpose();
        rhs += weight[j] * (gap[j] / level(j)) * b;
    }
    let coef = normal.cholesky()?.solve(&rhs);
    let mut field: Vec<f64> = (0..gap.len())
        .map(|j| coef.iter().zip(&basis(j)).map(|(c, b)| c * b).sum::<f64>())
        .collect();
    let total: f64 = fitted.iter().map(|&j| weight[j]).sum();
    let mean = fitted.iter().map(|&j| weight[j] * field[j]).sum::<f64>() / total;
    for f in &mut field {
        *f -= mean;
    }
    let square = fitted.iter().map(|&j| weight[j] * field[j] * field[j]);
    let gap = (square.sum::<f64>() / total).sqrt();
    Some(LowOrder {
        field,
        gap,
        share: low_order_share(gap),
    })
}

/// The share of the prior's disagreement at the largest scales (RMS `gap`) that the consensus
/// corrects: 1 − σ²/gap², σ = [`LOW_ORDER_CONSENSUS_ERROR`], the consensus's own error at those
/// scales, so that a prior as good as the consensus there is left as it is.
fn low_order_share(gap: f64) -> f64 {
    if gap <= LOW_ORDER_CONSENSUS_ERROR {
        return 0.0;
    }
    1.0 - (LOW_ORDER_CONSENSUS_ERROR / gap).powi(2)
}

/// Whether the consensus outvoted a regional error of the prior in bulk: more than
/// [`LOW_ORDER_MAX_OUTVOTED`] of the samples, unless they stray to both sides of the consensus
/// (the minority side at least [`BENT_MINORITY`] of them) and are at most
/// [`BENT_MAX_OUTVOTED`]: a prior bent as a whole (a tilt between floor and ceiling) strays
/// most where it is bent most, on both sides; a region strays to one.
fn outvoted_in_bulk(gap: &[f64], centre: f64, outvoted: &[bool]) -> bool {
    let (mut above, mut below) = (0usize, 0usize);
    for (&g, _) in gap.iter().zip(outvoted).filter(|(_, &o)| o) {
        if g > centre {
            above += 1;
        } else {
            below += 1;
        }
    }
    let count = (above + below) as f64;
    let n = gap.len() as f64;
    if count <= LOW_ORDER_MAX_OUTVOTED * n {
        return false;
    }
    count > BENT_MAX_OUTVOTED * n || (above.min(below) as f64) < BENT_MINORITY * count
}

/// The smaller side's share of the outvoted samples from which they count as a bend
/// ([`outvoted_in_bulk`]). Measured on the bench's rooms (docs/method.md, "The sphere's largest
/// scales"): a cap 30 % wrong on a fifth of the sphere under 1 %; the lower third 30 % too far
/// under 5 %, but 41–49 % in two rooms of ten, where the correction helped it; a ±20 % tilt
/// 17–50 %, or 0 where one side alone was outvoted.
const BENT_MINORITY: f64 = 0.1;

/// The share of samples outvoted on both sides above which the prior counts as wrong in bulk
/// anyway. The ±20 % tilt: up to 30 %.
const BENT_MAX_OUTVOTED: f64 = 0.35;

/// The share of the prior samples the consensus outvoted above which the prior's largest scales
/// are left as they are, unless the outvote strays both ways ([`outvoted_in_bulk`]): a regional
/// error that large (a cap 30 % wrong on a fifth of the sphere: 8–10 % outvoted; the lower
/// third, a quarter of the sphere, 30 % wrong: 16 %) has terms of degree 1 and 2 that the fit
/// takes for a bend. The bench's prior, with regions of 1–5 % of the sphere: 0.2–0.3 %.
const LOW_ORDER_MAX_OUTVOTED: f64 = 0.03;

/// The share of outvoted samples in a trust cell and the 8 around above which the cell's samples
/// are left out of [`low_order_gap`]'s fit.
const NEAR_OUTVOTED: f64 = 0.1;

/// Terms of the real spherical harmonics of degree ≤ 2.
const LOW_ORDER_TERMS: usize = 9;

/// The real spherical harmonics of degree ≤ 2 at unit direction `d` (unnormalised: 1; x, y, z;
/// xy, yz, zx, x² − y², 3z² − 1), the sphere's largest scales.
fn low_order_basis(d: [f64; 3]) -> [f64; LOW_ORDER_TERMS] {
    let [x, y, z] = d;
    [
        1.0,
        x,
        y,
        z,
        x * y,
        y * z,
        z * x,
        x * x - y * y,
        3.0 * z * z - 1.0,
    ]
}

/// The direction of a trust cell's centre ([`TRUST_ROWS`] × 2·[`TRUST_ROWS`] ERP grid).
fn cell_direction(cell: u32) -> [f64; 3] {
    let cols = 2 * TRUST_ROWS;
    let (row, col) = (cell as usize / cols, cell as usize % cols);
    let d = crate::sphere::lonlat_direction(
        crate::sphere::column_longitude(col as f64, cols),
        crate::sphere::row_latitude(row as f64, TRUST_ROWS),
    );
    [d.x, d.y, d.z]
}

/// The consensus's own error, relative, at the sphere's largest scales (spherical harmonics of
/// degree ≤ 2), below which the prior's disagreement there is not corrected
/// ([`low_order_share`]). Measured on 4 synthetic rooms at 2K under content errors
/// (docs/method.md, "The sphere's largest scales"): the stitch without the prior differed from
/// the truth there by 0.008–0.010 RMS, as much as the bench's prior (±3 % smooth error: 0.008).
const LOW_ORDER_CONSENSUS_ERROR: f64 = 0.008;

/// The share of the tangents' low-frequency disagreement with the prior that the data support:
/// var_p/(var_p + var_c) = 1 − var_c/var_gap. var_gap is the robust variance ((1.4826·median
/// |g|)²) of the low-passed disagreement `gap` at the samples with a consensus variance
/// (`variance(j)`, [`super::Problem::consensus_variance`]); var_c is the mean of those
/// variances over the samples whose gap lies within [`EVIDENCE_INLIER`] robust scales (a
/// regional error of the prior, which the judgement outvotes, must not count as the consensus's
/// uncertainty, nor, by the median, as the prior's smooth error), counted
/// [`CONSENSUS_VARIANCE_BIAS`] times (`robust_scale` keeps var_gap above 0). 0 without such
/// samples.
fn evidence_share(gap: &[f64], variance: impl Fn(usize) -> Option<f64>) -> f64 {
    let measured: Vec<(f64, f64)> = (0..gap.len())
        .filter_map(|j| variance(j).map(|v| (gap[j], v)))
        .collect();
    if measured.is_empty() {
        return 0.0;
    }
    let gaps: Vec<f64> = measured.iter().map(|m| m.0).collect();
    let sigma = super::robust_scale(&gaps);
    let inliers: Vec<f64> = measured
        .iter()
        .filter(|m| m.0.abs() <= EVIDENCE_INLIER * sigma)
        .map(|m| m.1)
        .collect();
    if inliers.is_empty() {
        return 0.0;
    }
    let var_c = CONSENSUS_VARIANCE_BIAS * inliers.iter().sum::<f64>() / inliers.len() as f64;
    (1.0 - var_c / (sigma * sigma)).clamp(0.0, 1.0)
}

/// How many times the consensus variance measured after the schedule's first level counts in
/// [`evidence_share`]. That level has already pulled the tangents towards each other, so their
/// spread understates their consensus's error. Measured on 4 synthetic rooms at 2K and 4K with
/// priors of ±3, ±6 and ±10 % smooth error (docs/method.md, "The prior's own quality"): 1 made
/// the bench's ±3 % prior 0.0086 → 0.0091 at 4K (the share 0.18 → 0.44); 2 keeps it within
/// 0.0002 at both sizes and still takes the ±10 % prior from 0.0209 / 0.0216 to 0.0147 / 0.0150.
const CONSENSUS_VARIANCE_BIAS: f64 = 2.0;

/// The median number of tangents seeing a prior sample (its own and its views) from which the
/// fusion weighs the prior's quality by [`evidence_share`]: 6 on the default layout (padding
/// 0.7), 4 on the paper's (0.3), where at 1K it raised the share on a good prior (0.16 → 0.55
/// in one room of four, 0.0090 → 0.0134).
const EVIDENCE_MIN_VIEWS: usize = 5;

/// A prior sample is outvoted by the tangents' consensus when its own gap and the low-passed
/// one, of one sign, exceed this many of the consensus's standard errors (√var_c, as in
/// [`evidence_share`]) and the low-passed one also [`OUTVOTE_RELATIVE_GAP`] of the disparity.
/// Measured on 4 synthetic rooms under content errors (docs/method.md, "Outvoted by the
/// consensus"): 2 also outvoted the good prior where the consensus was off (0.0119 → 0.0135 in
/// one room at 2K); 3 and 4 gave the wrong prior the same gain.
const OUTVOTE_STANDARD_ERRORS: f64 = 3.0;

/// The tangents' relative spread above which their consensus outvotes nothing: the synthetic
/// content errors give 0.015-0.019, the shared real networks 0.05-0.16. Those real networks err
/// alike in overlapping tiles, so their consensus looks surer than it is: without this bound it
/// outvoted a median 22 % (up to 46 %) of a real prior's samples on the 15 shared panoramas
/// (docs/method.md, "Outvoted by the consensus").
const OUTVOTE_MAX_SPREAD: f64 = 0.03;

/// The low-passed gap, relative to the disparity, below which a prior sample is never outvoted
/// by the consensus: twice the simulated panoramic network's smooth error. Without it the
/// consensus's own errors under content errors, which its spread understates, outvoted 8 % of
/// a good prior's samples in one room at 4K (0.0120 → 0.0127); with it 0.7 %.
const OUTVOTE_RELATIVE_GAP: f64 = 0.06;

/// Gaps within this many robust scales count in [`evidence_share`]'s consensus variance.
const EVIDENCE_INLIER: f64 = 2.5;

/// y ← y − (a·x + b), the weighted least-squares line of y on x (weights `w`).
fn remove_line(x: &[f64], y: &mut [f64], w: &[f64]) {
    let total: f64 = w.iter().sum();
    if total <= 0.0 {
        return;
    }
    let mean = |v: &[f64]| w.iter().zip(v).map(|(w, v)| w * v).sum::<f64>() / total;
    let (mx, my) = (mean(x), mean(y));
    let (mut cxy, mut cxx) = (0.0, 0.0);
    for ((&wk, &xk), &yk) in w.iter().zip(x).zip(y.iter()) {
        cxy += wk * (xk - mx) * (yk - my);
        cxx += wk * (xk - mx) * (xk - mx);
    }
    let slope = if cxx > 0.0 { cxy / cxx } else { 0.0 };
    for (yk, &xk) in y.iter_mut().zip(x) {
        *yk -= my + slope * (xk - mx);
    }
}

/// The pixels of each of `tangents` tangents of `pixels` pixels whose hash passes `threshold`
/// (the prior samples' deterministic draw), kept for the next call with the same arguments: a
/// scan hashes every pixel (45 M at 8K, 60 ms on 2 cores), while the samples are a fixed budget.
fn sample_pixels(tangents: usize, pixels: usize, threshold: u64) -> Arc<Vec<Vec<u32>>> {
    type Kept = Vec<((usize, usize, u64), Arc<Vec<Vec<u32>>>)>;
    static KEPT: Mutex<Kept> = Mutex::new(Vec::new());
    let key = (tangents, pixels, threshold);
    if let Some((_, hit)) = KEPT
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .iter()
        .find(|(k, _)| *k == key)
    {
        return Arc::clone(hit);
    }
    let chosen: Vec<Vec<u32>> = (0..tangents)
        .into_par_iter()
        .map(|t| {
            (0..pixels as u32)
                .filter(|&p| {
                    splitmix64(PRIOR_SALT ^ ((t as u64) << 32) ^ u64::from(p)) <= threshold
                })
                .collect()
        })
        .collect();
    let chosen = Arc::new(chosen);
    let mut kept = KEPT.lock().unwrap_or_else(PoisonError::into_inner);
    kept.push((key, Arc::clone(&chosen)));
    if kept.len() > SAMPLE_DRAWS_KEPT {
        kept.remove(0);
    }
    chosen
}

/// How many draws of prior sample pixels are kept (one per layout size and sample fraction).
const SAMPLE_DRAWS_KEPT: usize = 4;

/// Mean of the finite values of `map` (h×w) on a (2·reach + 1)² window of taps `stride` apart
/// around (x, y), clamped to the image; None when fewer than half the taps are finite.
fn window_mean(
    map: &[f32],
    w: usize,
    h: usize,
    x: usize,
    y: usize,
    reach: usize,
    stride: usize,
) -> Option<f32> {
    if reach == 0 {
        return Some(map[y * w + x]);
    }
    let span = (reach * stride) as isize;
    let (mut sum, mut count, mut taps) = (0.0f64, 0usize, 0usize);
    for dy in (-span..=span).step_by(stride) {
        let yy = (y as isize + dy).clamp(0, h as isize - 1) as usize;
        for dx in (-span..=span).step_by(stride) {
            let xx = (x as isize + dx).clamp(0, w as isize - 1) as usize;
            taps += 1;
            let v = map[yy * w + xx];
            if v.is_finite() {
                sum += f64::from(v);
                count += 1;
            }
        }
    }
    (2 * count >= taps).then(|| (sum / count as f64) as f32)
}

/// What an alignment fitted to the prior.
#[derive(Debug, Clone, PartialEq)]
pub struct PriorFit {
    /// (a, b): the prior P maps into the result's units as a·P + b (for an absolute prior
    /// (1, 0) up to rounding: the result is in its units).
    pub affine: (f64, f64),
    /// Prior samples used.
    pub samples: usize,
    /// Fraction of their confidence-weighted pull the IRLS weights took away: samples whose
    /// weight fell below ½ count as outvoted.
    pub outvoted: f64,
    /// The prior term's weight.
    pub weight: f64,
    /// Median |residual| of the prior samples at the end, in standardised units.
    pub residual: f64,
    /// The tangents' relative spread where two or more see a prior sample, after the
    /// schedule's first level (None when it was not measured: a schedule of one level, or no
    /// sample seen twice).
    pub tangent_spread: Option<f64>,
    /// The share of the tangents' low-frequency disagreement with the prior that moved it
    /// before it joined ([`TRUSTED_SPREAD`]; 0: the prior as given).
    pub tangent_share: f64,
    /// Share of the prior samples the tangents' consensus outvoted before the prior joined (far
    /// outside the consensus's uncertainty; their confidence set to 0).
    pub consensus_outvoted: f64,
    /// The prior's disagreement with that consensus at the sphere's largest scales (relative
    /// RMS over the spherical harmonics of degree ≤ 2; 0 when not measured).
    pub low_order_gap: f64,
    /// The share of that disagreement that moved the prior before it joined (0: none).
    pub low_order_share: f64,
}

#[cfg(test)]
mod tests {
    use super::super::*;
    use super::*;
    use crate::sphere::ErpGrid;
    use nalgebra::Vector3;

    /// The true spherical disparity of the test scene in direction `d` (smooth, positive).
    fn truth(d: &Vector3<f64>) -> f64 {
        1.0 / (2.0 + 0.6 * d.x + 0.4 * d.y * d.z - 0.3 * d.z)
    }

    /// Tangent maps of `layout`: the truth through a per-tangent affine map in perspective
    /// disparity (a·D + b·f), the error a network makes.
    fn tangents(layout: &Layout) -> Vec<f32> {
        maps_of(layout, |t, cam, x, y| {
            let (a, b) = (0.6 + 0.1 * (t % 7) as f64, 0.05 * (t % 5) as f64 - 0.1);
            a * truth(&cam.pixel_direction(x, y)) + b * cam.spherical_factor(x, y)
        })
    }

    /// Tangent maps of `layout` with `value(t, camera, x, y)` at pixel (x, y) of tangent t.
    fn maps_of(
        layout: &Layout,
        value: impl Fn(usize, &crate::camera::TangentCamera, f64, f64) -> f64,
    ) -> Vec<f32> {
        let (h, w) = layout.tangent_shape();
        let mut maps = Vec::with_capacity(layout.cameras.len() * h * w);
        for (t, cam) in layout.cameras.iter().enumerate() {
            for y in 0..h {
                for x in 0..w {
                    maps.push(value(t, cam, x as f64, y as f64) as f32);
                }
            }
        }
        maps
    }

    /// The truth on an ERP grid of `height` rows, times `wrong(d)`.
    fn prior_map(height: usize, absolute: bool, wrong: impl Fn(&Vector3<f64>) -> f64) -> Prior {
        let grid = ErpGrid::new(height, 2 * height);
        let mut values = Vec::with_capacity(2 * height * height);
        for r in 0..height {
            for c in 0..2 * height {
                let d = grid.direction(r, c);
                values.push((truth(&d) * wrong(&d)) as f32);
            }
        }
        Prior {
            values,
            confidence: None,
            height,
            width: 2 * height,
            absolute,
        }
    }

    fn setup(energy: Energy) -> (Layout, Vec<f32>, Options) {
        let layout = Layout::icosahedron(256, 0.3, None).expect("layout");
        let maps = tangents(&layout);
        let mut options = Options::new(energy, Solver::Newton);
        options.sample_fraction = 0.05;
        (layout, maps, options)
    }

    /// Relative errors of aligned `maps` against the truth, after the best global affine map
    /// when `relative`.
    fn errors(layout: &Layout, maps: &[f32], relative: bool) -> Vec<(Vector3<f64>, f64)> {
        let (h, w) = layout.tangent_shape();
        let mut pairs = Vec::new();
        for (t, cam) in layout.cameras.iter().enumerate() {
            for y in (0..h).step_by(3) {
                for x in (0..w).step_by(3) {
                    let d = cam.pixel_direction(x as f64, y as f64);
                    pairs.push((d, truth(&d), f64::from(maps[t * h * w + y * w + x])));
                }
            }
        }
        let (a, b) = if relative {
            // Least squares v ≈ a·truth + b.
            let n = pairs.len() as f64;
            let (sx, sy) = pairs
                .iter()
                .fold((0.0, 0.0), |(sx, sy), p| (sx + p.1, sy + p.2));
            let (mx, my) = (sx / n, sy / n);
            let (sxx, sxy) = pairs.iter().fold((0.0, 0.0), |(a, b), p| {
                (a + (p.1 - mx).powi(2), b + (p.1 - mx) * (p.2 - my))
            });
            let a = sxy / sxx;
            (a, my - a * mx)
        } else {
            (1.0, 0.0)
        };
        pairs
            .into_iter()
            .map(|(d, g, v)| (d, ((v - b) / a - g).abs() / g))
            .collect()
    }

    fn median(mut v: Vec<f64>) -> f64 {
        let mid = v.len() / 2;
        *v.select_nth_unstable_by(mid, f64::total_cmp).1
    }

    /// A point of `n` unknowns away from the identity: scales in [0.7, 1.3], offsets in
    /// [−0.5, 0.5], prior (α, β) alike.
    fn spread_point(n: usize) -> Vec<f64> {
        (0..n)
            .map(|i| {
                let u = ((i * 2_654_435_761) % 1000) as f64 / 1000.0;
                if i % 2 == 0 {
                    0.7 + 0.6 * u
                } else {
                    u - 0.5
                }
            })
            .collect()
    }

    #[test]
    fn gradient_with_prior_matches_finite_differences() {
        for energy in [Energy::Paper, Energy::Normalized] {
            let (layout, mut maps, options) = setup(energy);
            standardize(&layout, &mut maps, Offsets::Perspective).expect("standardize");
            let mut prior = prior_map(32, false, |d| 1.0 + 0.2 * d.x);
            prior.confidence = Some(
                (0..prior.values.len())
                    .map(|i| 0.2 + 0.8 * ((i * 7919) % 101) as f32 / 100.0)
                    .collect(),
            );
            let samples = PriorSamples::build(&layout, &maps, &prior, 0.05, 1.0).expect("prior");
            let overlaps = Overlaps::build(&layout, 0.05, 0.0);
            let mut params = options.level_params()[0];
            params.offsets = Offsets::Perspective;
            let mut problem = Problem::with_prior(
                &layout,
                maps.as_slice(),
                &overlaps,
                params,
                Some((&samples, 0.7)),
            );
            assert!(problem.prior_samples() > 100);
            let x = spread_point(problem.len());
            // The prior-only level's slope anchor, away from x's α, and its damping.
            problem.hold_prior_slope(0.3);
            problem.damp_fields(0.5);
            // IRLS weights that are not all 1.
            problem.reweight_prior(&x);
            assert_gradient_matches_finite_differences(&problem, &x, 5);
        }
    }

    /// The gradient at `x` against finite differences on every `stride`-th unknown and (α, β).
    fn assert_gradient_matches_finite_differences(problem: &Problem, x: &[f64], stride: usize) {
        let last = x.len() - 2;
        let at = (0..x.len()).step_by(stride).chain([last, last + 1]);
        crate::align::tests::assert_gradient_matches(problem, x, at, 1e-5);
    }

    /// Where a prior has holes does not change a level's pattern (so priors with holes in other
    /// places reuse the kept pattern and Newton analyses), and the Hessian on it still gives
    /// the gradient (checked against finite differences above with a full prior).
    #[test]
    fn priors_with_holes_elsewhere_share_the_pattern() {
        let (layout, mut maps, options) = setup(Energy::Normalized);
        standardize(&layout, &mut maps, Offsets::Perspective).expect("standardize");
        let mut params = options.level_params()[0];
        params.offsets = Offsets::Perspective;
        (params.cols, params.rows) = (9, 8);
        let empty = Overlaps::default();
        let holed = |from: f64, to: f64| {
            let mut prior = prior_map(32, false, |d| 1.0 + 0.2 * d.x);
            let n = prior.values.len() as f64;
            for v in &mut prior.values[(from * n) as usize..(to * n) as usize] {
                *v = f32::NAN;
            }
            PriorSamples::build(&layout, &maps, &prior, 1.0, 1.0).expect("prior")
        };
        let (a, b) = (holed(0.1, 0.3), holed(0.6, 0.8));
        let problem = |samples: &PriorSamples| {
            let mut p = Problem::with_prior(
                &layout,
                maps.as_slice(),
                &empty,
                params,
                Some((samples, 0.7)),
            );
            p.reweight_prior(&p.identity());
            p
        };
        let (pa, pb) = (problem(&a), problem(&b));
        assert!(pa.prior_samples() > 100 && pb.prior_samples() > 100);
        assert_ne!(pa.prior_groups.slices(), pb.prior_groups.slices());
        assert_eq!(pa.pattern.start, pb.pattern.start);
        assert_eq!(pa.pattern.col, pb.pattern.col);
        // The energy's gradient (through the pattern's Hessian) against central differences.
        assert_gradient_matches_finite_differences(&pa, &spread_point(pa.len()), 7);
    }

    /// A prior-only level's Newton step, per tangent with the Schur complement of (α, β), is
    /// the step of one Cholesky over all unknowns.
    #[test]
    fn the_per_tangent_newton_step_is_the_global_one() {
        let (layout, mut maps, options) = setup(Energy::Normalized);
        standardize(&layout, &mut maps, Offsets::Perspective).expect("standardize");
        let prior = prior_map(32, false, |d| 1.0 + 0.2 * d.x);
        let samples = PriorSamples::build(&layout, &maps, &prior, 1.0, 1.0).expect("prior");
        let mut params = options.level_params()[0];
        params.offsets = Offsets::Perspective;
        (params.cols, params.rows) = (5, 4);
        let empty = Overlaps::default();
        let mut problem = Problem::with_prior(
            &layout,
            maps.as_slice(),
            &empty,
            params,
            Some((&samples, 0.7)),
        );
        assert_eq!(problem.samples(), 0);
        let x = spread_point(problem.len());
        problem.hold_prior_slope(0.3);
        problem.reweight_prior(&x);
        let mut g = vec![0.0; x.len()];
        let _ = problem.energy(&x, Some(&mut g));
        let mut global = NewtonSystem::new(&problem).expect("global");
        let mut tangents = TangentSystems::new(&problem)
            .expect("per tangent")
            .expect("an arrow: no term between tangents");
        let a = global.step(&problem, &x, &g).expect("step");
        let b = tangents.step(&problem, &x, &g).expect("step");
        let scale = a.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let gap = a
            .iter()
            .zip(&b)
            .fold(0.0f64, |m, (u, v)| m.max((u - v).abs()));
        assert!(scale > 1e-3 && gap < 1e-9 * scale, "gap {gap} of {scale}");
        // With overlap samples the tangents share terms: the global system.
        let overlaps = Overlaps::build(&layout, 0.05, 0.0);
        let coupled = Problem::with_prior(
            &layout,
            maps.as_slice(),
            &overlaps,
            params,
            Some((&samples, 0.7)),
        );
        assert!(matches!(
            Newton::new(&coupled).expect("system"),
            Newton::Global(_)
        ));
        assert!(matches!(
            Newton::new(&problem).expect("system"),
            Newton::Tangents(_)
        ));
    }

    /// Exact tangents up to per-tangent affine maps and an exact absolute prior: the result is
    /// the truth in the prior's units, to the floor of the prior's resampling.
    #[test]
    fn perfect_prior_and_tangents_give_the_floor() {
        for (energy, solver) in [
            (Energy::Normalized, Solver::Newton),
            (Energy::Normalized, Solver::Lbfgs),
            (Energy::Paper, Solver::Newton),
        ] {
            let (layout, mut maps, mut options) = setup(energy);
            options.solver = solver;
            if solver == Solver::Lbfgs {
                options.iterations = 2000;
            }
            let prior = prior_map(64, true, |_| 1.0);
            let overlaps = Overlaps::build(&layout, options.sample_fraction, 0.0);
            let fit = align_with_prior(&layout, &mut maps, &overlaps, &options, Some(&prior))
                .expect("align")
                .prior
                .expect("a prior fit");
            let errs: Vec<f64> = errors(&layout, &maps, false)
                .into_iter()
                .map(|e| e.1)
                .collect();
            let med = median(errs.clone());
            assert!(
                med < 2e-3,
                "{energy:?} {solver:?}: median relative error {med}"
            );
            assert!((fit.affine.0 - 1.0).abs() < 1e-2, "{fit:?}");
            // The judgement is hard: a sample beyond 1.2 σ of the consensus weighs 0 even when
            // right (σ at least MIN_PRIOR_SCALE, here the resampling's floor), 0.15 of the pull
            // here. A perfect prior loses no more than that.
            if energy == Energy::Normalized {
                assert!(fit.outvoted < 0.2, "{fit:?}");
            }
        }
    }

    /// The prior-only level takes its samples' judgement from the schedule's last level, which
    /// made it on the same maps at its end; judging them afresh at the level's start gives the
    /// same weights (a prior wrong on a cap, so that some samples lose their pull) and result.
    #[test]
    fn the_prior_only_level_inherits_the_judgement_it_would_make() {
        let (layout, maps, mut options) = setup(Energy::Normalized);
        options.prior_scale_deg = 8.0; // a grid this small layout's prior samples support
        let prior = prior_map(64, false, |d| if d.x > 0.6 { 1.3 } else { 1.0 });
        let overlaps = Overlaps::build(&layout, options.sample_fraction, 0.0);
        let run = |afresh: bool| {
            JUDGE_AFRESH.with(|f| f.set(afresh));
            let mut out = maps.clone();
            let alignment = align_with_prior(&layout, &mut out, &overlaps, &options, Some(&prior));
            JUDGE_AFRESH.with(|f| f.set(false));
            (out, alignment.expect("align"))
        };
        let (inherited, a) = run(false);
        let (afresh, b) = run(true);
        let schedule = options.level_params().len();
        assert_eq!(a.levels.len(), schedule + 1, "the prior-only level ran");
        let weights = |al: &Alignment| {
            al.levels[schedule]
                .prior
                .as_ref()
                .expect("prior")
                .weights
                .clone()
        };
        let (wa, wb) = (weights(&a), weights(&b));
        assert!(wa.contains(&0.0) && wa.iter().any(|&w| w > 0.0));
        // The same samples trusted; the weights agree to the rounding of the f32 maps the
        // fresh judgement reads (the inherited one saw the fields in f64).
        let flips = wa
            .iter()
            .zip(&wb)
            .filter(|(x, y)| (**x == 0.0) != (**y == 0.0))
            .count();
        let apart = wa
            .iter()
            .zip(&wb)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max);
        assert_eq!(flips, 0);
        assert!(apart < 1e-3, "{apart}");
        let largest = inherited
            .iter()
            .zip(&afresh)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert!(largest < 1e-5, "{largest}");
    }

    /// A relative prior 30 % wrong on a cap of about a fifth of the sphere: the tangents agree
    /// with each other there, so the prior's samples lose their pull and the result stays at
    /// the truth (up to the global affine map).
    #[test]
    fn a_prior_with_a_regional_error_is_outvoted() {
        let (layout, maps, options) = setup(Energy::Normalized);
        let inside = |d: &Vector3<f64>| d.x > 0.6;
        let prior = prior_map(64, false, |d| if inside(d) { 1.3 } else { 1.0 });
        let overlaps = Overlaps::build(&layout, options.sample_fraction, 0.0);
        let mut with = maps.clone();
        let fit = align_with_prior(&layout, &mut with, &overlaps, &options, Some(&prior))
            .expect("align")
            .prior
            .expect("a prior fit");
        let errs = errors(&layout, &with, true);
        let region: Vec<f64> = errs.iter().filter(|e| inside(&e.0)).map(|e| e.1).collect();
        let med = median(region);
        assert!(
            med < 0.01,
            "median relative error in the wrong region {med}"
        );
        assert!(
            (0.1..0.4).contains(&fit.outvoted),
            "outvoted fraction {}",
            fit.outvoted
        );
    }

    /// How far `values` are from a line in `truth`: the RMS residual of their least-squares line
    /// on it, relative to their own standard deviation.
    fn off_the_line(truth: &[f64], values: &[f64]) -> f64 {
        let mut residual = values.to_vec();
        remove_line(truth, &mut residual, &vec![1.0; truth.len()]);
        let n = values.len() as f64;
        let mean = values.iter().sum::<f64>() / n;
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
        (residual.iter().map(|r| r * r).sum::<f64>() / n / var).sqrt()
    }

    /// Maps read with a hole (the range of flat indices reads NaN), as a transform gone
    /// non-finite would leave them.
    struct Holed<'a>(&'a [f32], std::ops::Range<usize>);
    impl MapValues for Holed<'_> {
        fn value(&self, index: usize) -> f32 {
            self.through(index, self.0[index])
        }
        fn through(&self, index: usize, raw: f32) -> f32 {
            if self.1.contains(&index) {
                f32::NAN
            } else {
                raw
            }
        }
    }

    /// Independently of a problem: the consensus at each of `samples` from the tangent maps
    /// (h×w), its own tangent's window value and its views' bilinear values.
    fn consensus_of<M: MapValues + ?Sized>(
        samples: &PriorSamples,
        maps: &M,
        h: usize,
        w: usize,
    ) -> Vec<Option<Consensus>> {
        (0..samples.len())
            .map(|k| {
                let own = f64::from(samples.tangent_value(k, maps, h * w));
                if !own.is_finite() {
                    return None;
                }
                let range = samples.view_start[k] as usize..samples.view_start[k + 1] as usize;
                let values: Vec<f64> = std::iter::once(own)
                    .chain(range.filter_map(|v| samples.view_value(v, maps, w, h)))
                    .collect();
                let n = values.len() as f64;
                let mean = values.iter().sum::<f64>() / n;
                let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
                Some(Consensus {
                    mean,
                    std: var.sqrt(),
                    seen_by: values.len(),
                })
            })
            .collect()
    }

    /// The consensus the alignment reads off a level's problem is the one the maps give, and
    /// the fused values the problem takes are the fused prior's.
    #[test]
    fn the_problems_consensus_is_the_maps() {
        let layout = Layout::icosahedron(256, 0.3, None).expect("layout");
        let (h, w) = layout.tangent_shape();
        let maps = tangents(&layout);
        let prior = prior_map(64, false, |d| 1.0 + 0.08 * d.x * d.y);
        let samples = PriorSamples::build(&layout, &maps, &prior, 0.05, 1.5).expect("samples");
        // A hole in tangent 3: samples there drop out of the problem, the others keep their
        // index.
        let maps = Holed(&maps, 3 * h * w..3 * h * w + 40 * w);
        let overlaps = Overlaps::build(&layout, 0.05, 0.0);
        let (_, _, options) = setup(Energy::Normalized);
        let params = options.level_params()[1];
        let mut problem =
            Problem::with_prior(&layout, &maps, &overlaps, params, Some((&samples, 1.0)));
        let expected = consensus_of(&samples, &maps, h, w);
        let got = problem
            .prior_consensus(samples.len())
            .expect("a prior term");
        assert!(
            expected.iter().any(Option::is_none),
            "the hole drops samples"
        );
        assert_eq!(got.len(), expected.len());
        for (g, e) in got.iter().zip(&expected) {
            match (g, e) {
                (None, None) => {}
                (Some(g), Some(e)) => {
                    assert_eq!(g.seen_by, e.seen_by);
                    assert!((g.mean - e.mean).abs() <= 1e-12 * e.mean.abs().max(1.0));
                    assert!((g.std - e.std).abs() <= 1e-9 * e.mean.abs().max(1.0));
                }
                _ => panic!("{g:?} vs {e:?}"),
            }
        }
        let values: Vec<f64> = (0..samples.len()).map(|k| 0.5 * k as f64).collect();
        problem.set_prior_values(&values);
        let term = problem.prior.as_ref().expect("a prior term");
        for (sample, &k) in term.samples.iter().zip(&term.source) {
            assert!((sample.p - values[k as usize]).abs() < f64::EPSILON);
        }
    }

    /// Tangents that agree with each other (here exactly the truth) move a prior with a smooth
    /// error of its own towards them in full: the fused values lie on a line in the truth, the
    /// prior's did not.
    #[test]
    fn consistent_tangents_take_the_prior_towards_them() {
        let layout = Layout::icosahedron(256, 0.3, None).expect("layout");
        let (h, w) = layout.tangent_shape();
        let maps = maps_of(&layout, |_, cam, x, y| truth(&cam.pixel_direction(x, y)));
        let prior = prior_map(64, false, |d| 1.0 + 0.08 * d.x * d.y + 0.05 * d.z);
        let samples = PriorSamples::build(&layout, &maps, &prior, 0.05, 1.5).expect("samples");
        let fusion = samples
            .fused(
                &consensus_of(&samples, maps.as_slice(), h, w),
                || None,
                (1.0, 0.0),
            )
            .expect("a fusion");
        assert!(fusion.spread < TRUSTED_SPREAD, "{}", fusion.spread);
        assert!((fusion.share - 1.0).abs() < 1e-12, "{}", fusion.share);
        let fused = fusion.samples.expect("fused samples");
        let at: Vec<f64> = (0..samples.len())
            .map(|k| f64::from(samples.tangent_value(k, maps.as_slice(), h * w)))
            .collect();
        let before = off_the_line(&at, &samples.value);
        let after = off_the_line(&at, &fused.value);
        assert!(before > 0.05, "the prior's own error {before}");
        assert!(after < 0.3 * before, "{before} -> {after}");
    }

    /// `prior_fusion` off: the alignment neither measures the tangents' spread nor moves the
    /// prior (auto, on the same consistent tangents, fuses in full).
    #[test]
    fn fusion_off_leaves_the_prior_unmeasured_and_unmoved() {
        let (layout, maps, mut options) = setup(Energy::Normalized);
        let prior = prior_map(64, false, |d| 1.0 + 0.08 * d.x * d.y);
        let overlaps = Overlaps::build(&layout, options.sample_fraction, 0.0);
        let mut fit = |fusion: PriorFusion| {
            options.prior_fusion = fusion;
            let mut out = maps.clone();
            align_with_prior(&layout, &mut out, &overlaps, &options, Some(&prior))
                .expect("align")
                .prior
                .expect("a prior fit")
        };
        let auto = fit(PriorFusion::Auto);
        assert!(
            auto.tangent_spread.is_some_and(|s| s < TRUSTED_SPREAD),
            "{auto:?}"
        );
        assert!((auto.tangent_share - 1.0).abs() < 1e-12, "{auto:?}");
        let off = fit(PriorFusion::Off);
        assert_eq!(off.tangent_spread, None);
        assert!(off.tangent_share.abs() < f64::EPSILON);
    }

    /// Tangents that disagree with each other by 10 % and more leave the prior as it is.
    #[test]
    fn inconsistent_tangents_leave_the_prior_as_it_is() {
        let layout = Layout::icosahedron(256, 0.3, None).expect("layout");
        let (h, w) = layout.tangent_shape();
        let maps = maps_of(&layout, |t, cam, x, y| {
            let tilt = 0.1 + 0.02 * (t % 5) as f64;
            truth(&cam.pixel_direction(x, y)) * (1.0 + tilt * (x / w as f64 - 0.5))
        });
        let prior = prior_map(64, false, |d| 1.0 + 0.08 * d.x * d.y);
        let samples = PriorSamples::build(&layout, &maps, &prior, 0.05, 1.5).expect("samples");
        let fusion = samples
            .fused(
                &consensus_of(&samples, maps.as_slice(), h, w),
                || None,
                (1.0, 0.0),
            )
            .expect("a fusion");
        assert!(fusion.spread > UNTRUSTED_SPREAD, "{}", fusion.spread);
        assert!(fusion.share <= 0.0, "{}", fusion.share);
        assert!(fusion.samples.is_none());
    }

    /// The consensus variance the fusion weighs the prior against, read off a level's problem:
    /// 0 where the tangents agree; with an offset c_t per tangent, Σ D_t²/(n(n − 1)) with D_t
    /// the mean over the trust cell and its neighbours of c_t minus the mean offset of the
    /// tangents that see each sample, which the oracle takes from the offsets and the samples'
    /// views alone (no map read).
    #[test]
    fn the_consensus_variance_is_that_of_the_tangents_offsets() {
        let layout = Layout::icosahedron(256, 0.3, None).expect("layout");
        let offset = |t: usize| 0.02 * (t % 5) as f64 - 0.04;
        let prior = prior_map(64, false, |_| 1.0);
        let overlaps = Overlaps::build(&layout, 0.05, 0.0);
        let (_, _, options) = setup(Energy::Normalized);
        let params = options.level_params()[1];
        let variance = |maps: &[f32]| {
            let samples = PriorSamples::build(&layout, maps, &prior, 0.05, 1.5).expect("samples");
            let problem =
                Problem::with_prior(&layout, maps, &overlaps, params, Some((&samples, 1.0)));
            let got = problem
                .consensus_variance(samples.len())
                .expect("a prior term");
            (samples, got)
        };
        // A flat scene: the samples' own window means and their views' bilinear values then
        // differ by the offsets alone.
        let maps = maps_of(&layout, |t, _, _, _| 0.5 + offset(t));
        let (samples, got) = variance(&maps);
        let tangents = layout.cameras.len();
        let cells = TRUST_ROWS * 2 * TRUST_ROWS;
        let (mut sum, mut count) = (vec![0.0; cells * tangents], vec![0.0; cells * tangents]);
        for k in 0..samples.len() {
            let range = samples.view_start[k] as usize..samples.view_start[k + 1] as usize;
            let seen: Vec<usize> = std::iter::once(samples.tangent[k])
                .chain(samples.view_tangent[range].iter().copied())
                .map(usize::from)
                .collect();
            if seen.len() < 2 {
                continue;
            }
            let mean = seen.iter().map(|&t| offset(t)).sum::<f64>() / seen.len() as f64;
            for &t in &seen {
                sum[samples.cell[k] as usize * tangents + t] += offset(t) - mean;
                count[samples.cell[k] as usize * tangents + t] += 1.0;
            }
        }
        let (rows, cols) = (TRUST_ROWS as isize, 2 * TRUST_ROWS as isize);
        let mut checked = 0;
        for (k, v) in got.iter().enumerate() {
            let (r, c) = (
                samples.cell[k] as isize / cols,
                samples.cell[k] as isize % cols,
            );
            let mut d = vec![(0.0, 0.0); tangents];
            for rr in (r - 1).max(0)..=(r + 1).min(rows - 1) {
                for dc in -1..=1 {
                    let cell = (rr * cols + (c + dc).rem_euclid(cols)) as usize;
                    for (t, d) in d.iter_mut().enumerate() {
                        d.0 += sum[cell * tangents + t];
                        d.1 += count[cell * tangents + t];
                    }
                }
            }
            let devs: Vec<f64> = d.iter().filter(|d| d.1 > 0.0).map(|d| d.0 / d.1).collect();
            let n = devs.len() as f64;
            let want =
                (n >= 2.0).then(|| devs.iter().map(|d| d * d).sum::<f64>() / (n * (n - 1.0)));
            match (v, want) {
                (Some(v), Some(want)) => {
                    assert!((v - want).abs() <= 1e-4 * want + 1e-12, "{v} vs {want}");
                    checked += 1;
                }
                (v, want) => assert_eq!(v.is_some(), want.is_some(), "sample {k}"),
            }
        }
        assert!(
            checked > samples.len() / 2,
            "{checked} of {}",
            samples.len()
        );
        // Consistent tangents: what is left is the window mean against the bilinear read of
        // a smooth truth, a hundredth of the offsets' variance.
        let mut offsets: Vec<f64> = got.iter().flatten().copied().collect();
        let mid = offsets.len() / 2;
        let typical = *offsets.select_nth_unstable_by(mid, f64::total_cmp).1;
        let exact = maps_of(&layout, |_, cam, x, y| truth(&cam.pixel_direction(x, y)));
        let (_, agreed) = variance(&exact);
        let worst = agreed.iter().flatten().fold(0.0_f64, |a, &v| a.max(v));
        assert!(
            worst < 0.02 * typical,
            "consistent tangents: {worst} vs {typical}"
        );
    }

    /// The largest scales' fit recovers a bend of degree ≤ 2 exactly, leaves out a regional error
    /// that stands out of the gap's distribution and the samples without weight.
    #[test]
    fn the_prior_s_largest_scales_are_fitted_and_a_regional_error_left_out() {
        // One sample at every trust cell's centre, with a disparity level that varies, so that
        // the fit's relative gap (gap / level) is what it reads.
        let cells: Vec<u32> = (0..(2 * TRUST_ROWS * TRUST_ROWS) as u32).collect();
        let dirs: Vec<[f64; 3]> = cells.iter().map(|&c| cell_direction(c)).collect();
        let level: Vec<f64> = (0..cells.len())
            .map(|j| 1.0 + 0.5 * (j % 7) as f64)
            .collect();
        let bend =
            |d: [f64; 3]| 0.02 * d[0] - 0.03 * d[1] * d[2] + 0.01 * (3.0 * d[2] * d[2] - 1.0);
        let weight = vec![1.0; cells.len()];
        let fit = |relative: &dyn Fn(usize) -> f64| {
            let gap: Vec<f64> = (0..cells.len()).map(|j| relative(j) * level[j]).collect();
            low_order_gap(&gap, &gap, |j| level[j], &weight, &cells).expect("a fit")
        };
        // A bend of degree ≤ 2 plus a constant (the prior's units): the field is the bend minus
        // its mean over the cells, and its RMS theirs (the oracle: the bend evaluated directly).
        let bent = fit(&|j| bend(dirs[j]) + 0.05);
        let mean = dirs.iter().map(|&d| bend(d)).sum::<f64>() / dirs.len() as f64;
        let mut square = 0.0;
        for (f, &d) in bent.field.iter().zip(&dirs) {
            assert!(
                (f - (bend(d) - mean)).abs() < 1e-9,
                "{f} vs {}",
                bend(d) - mean
            );
            square += (bend(d) - mean).powi(2);
        }
        assert!((bent.gap - (square / dirs.len() as f64).sqrt()).abs() < 1e-9);
        assert!(
            bent.share > 0.5 && (bent.share - low_order_share(bent.gap)).abs() < 1e-15,
            "{} {}",
            bent.gap,
            bent.share
        );
        // The same prior 30 % wrong on a cap around +x (a seventh of the cells): the cap stands
        // out of the gap's distribution and is left out, so the fit is still the bend's.
        let cap = |d: [f64; 3]| d[0] > 0.6;
        let share = dirs.iter().filter(|&&d| cap(d)).count() as f64 / dirs.len() as f64;
        assert!((0.1..0.3).contains(&share), "{share}");
        let capped = fit(&|j| bend(dirs[j]) + if cap(dirs[j]) { 0.3 } else { 0.0 });
        assert!(
            (capped.gap - bent.gap).abs() < 0.1 * bent.gap,
            "{} vs {}",
            capped.gap,
            bent.gap
        );
        let near = capped.field.iter().zip(&bent.field);
        assert!(near.into_iter().all(|(a, b)| (a - b).abs() < 0.01));
        // Without the bend the cap alone is no bend: nothing to correct.
        let alone = fit(&|j| if cap(dirs[j]) { 0.3 } else { 0.0 });
        assert!(alone.gap < 1e-9 && alone.share <= 0.0, "{}", alone.gap);
        // A prior as good as the consensus there is left as it is; beyond, 1 − (σ/gap)².
        assert!(low_order_share(LOW_ORDER_CONSENSUS_ERROR) <= 0.0);
        assert!((low_order_share(2.0 * LOW_ORDER_CONSENSUS_ERROR) - 0.75).abs() < 1e-12);
        // Too few samples to fit: none. A sample without weight is not fitted.
        let few = &cells[..50];
        assert!(low_order_gap(&[0.1; 50], &[0.1; 50], |_| 1.0, &[1.0; 50], few).is_none());
        let mut unweighted = weight.clone();
        unweighted
            .iter_mut()
            .zip(&dirs)
            .for_each(|(w, &d)| *w = if cap(d) { 0.0 } else { 1.0 });
        let gap: Vec<f64> = (0..cells.len())
            .map(|j| if cap(dirs[j]) { 5.0 } else { 0.0 })
            .collect();
        let blind = low_order_gap(&gap, &gap, |_| 1.0, &unweighted, &cells).expect("a fit");
        assert!(blind.gap < 1e-9, "{}", blind.gap);
    }

    /// The fit's weights: confidence over views, 0 where one tangent alone sees the sample, where
    /// it was outvoted and beside a neighbourhood more than 10 % outvoted.
    #[test]
    fn low_order_weights_leave_out_what_the_consensus_cannot_judge() {
        // Cells 0..60 are the top row; 100 samples in cell 200 (row 3), 10 % of them outvoted.
        let cells: Vec<u32> = [0, 1, 2].into_iter().chain([200; 100]).collect();
        let n = cells.len();
        let shared: Vec<bool> = (0..n).map(|j| j != 1).collect();
        let outvoted: Vec<bool> = (0..n).map(|j| (3..13).contains(&j)).collect();
        let conf = vec![0.5; n];
        let views = |j: usize| if j == 2 { 4 } else { 2 };
        let w = low_order_weights(&shared, &outvoted, &conf, &cells, views);
        assert!((w[0] - 0.25).abs() < 1e-12); // confidence over its views
        assert!(w[1] == 0.0); // one tangent alone sees it
        assert!((w[2] - 0.125).abs() < 1e-12);
        assert!(w[3] == 0.0); // outvoted
        assert!((w[20] - 0.25).abs() < 1e-12); // 10 % outvoted around it: at the bound, kept
        let more: Vec<bool> = (0..n).map(|j| (3..14).contains(&j)).collect();
        let w = low_order_weights(&shared, &more, &conf, &cells, views);
        assert!(w[20] == 0.0 && w[0] > 0.0); // 11 %: a regional error's rest
    }

    /// A prior outvoted on more than 3 % of its samples is a regional error, unless they stray to
    /// both sides (a bend; a tenth of them or more on the smaller side) and are at most 35 % of
    /// them.
    #[test]
    fn an_outvote_in_bulk_is_regional_unless_it_strays_both_ways() {
        // 1000 samples; `up` of them outvoted above the centre 0.1, `down` below it.
        let case = |up: usize, down: usize| {
            let gap: Vec<f64> = (0..1000)
                .map(|j| match j {
                    j if j < up => 0.5,
                    j if j < up + down => -0.3,
                    _ => 0.1,
                })
                .collect();
            let outvoted: Vec<bool> = (0..1000).map(|j| j < up + down).collect();
            outvoted_in_bulk(&gap, 0.1, &outvoted)
        };
        assert!(!case(30, 0)); // 3 %: at the bound, not in bulk
        assert!(case(31, 0)); // one-sided beyond it: a region
        assert!(case(91, 9)); // 10 %, 9 % of them on the other side: still a region
        assert!(!case(90, 10)); // 10 %, a tenth on the other side: a bend
        assert!(!case(175, 175)); // 35 %, balanced: at the bound, a bend
        assert!(case(176, 175)); // beyond it: regional either way
        assert!(!case(0, 0));
    }

    /// The consensus outvotes a prior sample only beyond both bounds, on its own and low-passed,
    /// of one sign, and only where its variance was measured.
    #[test]
    fn the_consensus_outvotes_only_far_and_coherent_disagreement() {
        // Consensus standard error 0.01 everywhere, disparity level 1: the bound is
        // max(3 · 0.01, 0.06 · 1) = 0.06 for the low-passed gap, 0.03 for the sample's own.
        let var_c = |_| Some(1e-4);
        let level = |_| 1.0;
        let case = |own: f64, low: f64| consensus_outvotes(&[own], 0.0, &[low], var_c, level)[0];
        assert!(case(0.1, 0.08)); // far beyond both bounds, one sign
        assert!(case(-0.1, -0.08));
        assert!(!case(0.1, 0.05)); // low-passed gap within the prior's plausible smooth error
        assert!(!case(0.02, 0.08)); // the sample itself agrees (a region's neighbour)
        assert!(!case(-0.1, 0.08)); // of opposite signs: noise, not the prior's error
                                    // A larger consensus error raises the bound past the relative one: 3 · 0.05 = 0.15.
        let loose = |_| Some(0.05 * 0.05);
        assert!(!consensus_outvotes(&[0.2], 0.0, &[0.1], loose, level)[0]);
        assert!(consensus_outvotes(&[0.2], 0.0, &[0.16], loose, level)[0]);
        // A darker level lowers the relative bound: 0.06 · 0.5 = 0.03 < 0.05.
        assert!(consensus_outvotes(&[0.1], 0.0, &[0.05], var_c, |_| 0.5)[0]);
        // Not measured (too few views): never outvoted. The gap is taken from its centre.
        assert!(!consensus_outvotes(&[1.0], 0.0, &[1.0], |_| None, level)[0]);
        assert!(!consensus_outvotes(&[1.0], 0.99, &[0.08], var_c, level)[0]);
    }

    /// The evidence share is 1 − var_c/var_gap (var_c counted [`CONSENSUS_VARIANCE_BIAS`]
    /// times), with the gap's variance taken robustly: a
    /// regional error of the prior (a fifth of the samples far off) moves it little, while a
    /// consensus as uncertain as the gap leaves nothing to the tangents.
    #[test]
    fn the_evidence_share_weighs_the_prior_against_the_consensus() {
        // A gap whose robust scale is known: |g| spread evenly in (0, 2σ·0.6745·2), so the
        // median |g| is 0.6745·σ and 1.4826·median = σ.
        let sigma: f64 = 0.01;
        let n: u32 = 1000;
        let gap: Vec<f64> = (0..n)
            .map(|j| {
                let magnitude = 2.0 * 0.674_49 * sigma * (f64::from(j) + 0.5) / f64::from(n);
                if j.is_multiple_of(2) {
                    magnitude
                } else {
                    -magnitude
                }
            })
            .collect();
        // A measured consensus variance counts CONSENSUS_VARIANCE_BIAS times: 0.3 σ² in all.
        let var_c = 0.3 * sigma * sigma / CONSENSUS_VARIANCE_BIAS;
        let share = evidence_share(&gap, |_| Some(var_c));
        assert!((share - 0.7).abs() < 0.01, "{share}");
        let raw = evidence_share(&gap, |_| Some(0.3 * sigma * sigma));
        let want = 1.0 - CONSENSUS_VARIANCE_BIAS * 0.3;
        assert!((raw - want).abs() < 0.01, "{raw} vs {want}");
        // A regional error: a fifth of the samples 30 σ off, with a larger consensus variance
        // there (content the tangents disagree on), counted neither in var_gap's median much
        // nor in var_c.
        let mut wrong = gap.clone();
        for g in wrong.iter_mut().step_by(5) {
            *g += 30.0 * sigma;
        }
        let region = |j: usize| {
            Some(if j.is_multiple_of(5) {
                100.0 * var_c
            } else {
                var_c
            })
        };
        let outvoted = evidence_share(&wrong, region);
        assert!((0.6..0.85).contains(&outvoted), "{outvoted}");
        let as_uncertain = sigma * sigma / CONSENSUS_VARIANCE_BIAS;
        assert!(evidence_share(&gap, |_| Some(as_uncertain)).abs() < 0.02);
        assert!(evidence_share(&gap, |_| None).abs() < f64::EPSILON);
        assert!((evidence_share(&gap, |_| Some(0.0)) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn remove_line_leaves_the_residual_of_the_weighted_fit() {
        let x = [0.0, 1.0, 2.0, 3.0, 10.0];
        let mut y: Vec<f64> = x.iter().map(|x| 2.0 * x - 1.0).collect();
        y[4] += 5.0; // an outlier with no weight
        remove_line(&x, &mut y, &[1.0, 1.0, 1.0, 1.0, 0.0]);
        for r in &y[..4] {
            assert!(r.abs() < 1e-12, "{y:?}");
        }
        assert!((y[4] - 5.0).abs() < 1e-12, "{y:?}");
    }
}
