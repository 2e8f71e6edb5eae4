//! Row-by-row blends of per-tangent maps on the ERP grid: mean, nearest face, weighted.
//!
//! Each ERP row's runs are sampled into a buffer the size of the run (it stays in L1) and
//! accumulated face by face into per-pixel sums, without branches; the spread (the
//! `confidence` output) comes from the same single pass.

use super::WeightMaps;
use crate::align::Prior;
use crate::layout::Layout;
use crate::resample::{ErpTaps, Run, Sampling};
use rayon::prelude::*;

/// One ERP row's samples, face by face: the row's runs and, per tap (in run order), the face's
/// value there (NaN = invalid), its blending weight (none stored: all 1) and its nearness rank
/// at its pixel (0 = nearest axis).
#[derive(Debug, Default, Clone)]
pub(crate) struct RowSamples {
    pub runs: Vec<Run>,
    pub values: Vec<f32>,
    pub weights: Vec<f32>,
    pub ranks: Vec<u8>,
}

impl RowSamples {
    /// The samples of ERP row `i` of tangent images through `taps`, with per-tap `weights`,
    /// and with ranks if `ranks` (only the nearest-face statistics need them).
    ///
    /// # Panics
    /// If `tangents` or `weights` do not belong to `taps`.
    pub(crate) fn fill_from_taps(
        &mut self,
        taps: &ErpTaps,
        tangents: &[f32],
        weights: Option<&WeightMaps>,
        ranks: bool,
        i: usize,
    ) {
        self.runs.clear();
        self.runs.extend_from_slice(taps.runs(i));
        if let Some(w) = weights {
            taps.sample_many(
                [tangents, w.maps()],
                Sampling::DepthEdges,
                i,
                [&mut self.values, &mut self.weights],
            );
        } else {
            taps.sample(tangents, Sampling::DepthEdges, i, &mut self.values);
            self.weights.clear();
        }
        self.ranks.clear();
        if ranks {
            taps.ranks(i, &mut self.ranks);
        }
    }

    #[expect(
        clippy::inline_always,
        reason = "per-pixel kernel; inlined it measured faster"
    )]
    #[inline(always)]
    pub(crate) fn weight(&self, t: usize) -> f32 {
        if self.weights.is_empty() {
            1.0
        } else {
            self.weights[t]
        }
    }
}

/// Per-pixel statistics of the valid (finite) samples of one ERP row, accumulated run by run;
/// NaN where a pixel has none.
///
/// Sums are kept relative to each pixel's first valid sample (a shift close to the mean), so the
/// spread comes from the same single pass without the cancellation of Σv² − n·mean²; f32 is
/// exact enough for a handful of samples per pixel.
#[derive(Debug, Default)]
pub(crate) struct RowStats {
    extras: Extras,
    count: Vec<f32>,
    shift: Vec<f32>,
    shifted_sum: Vec<f32>,
    shifted_squares: Vec<f32>,
    weight_sum: Vec<f32>,
    weighted_sum: Vec<f32>,
    rank: Vec<u8>,
    /// The sample of the nearest valid face (with [`Extras::nearest`]).
    pub nearest: Vec<f32>,
    /// Unweighted mean.
    pub mean: Vec<f32>,
    /// Σ w·v / Σ w; the plain mean where every valid sample has weight 0 (radial weights vanish
    /// near the icosahedron's vertices, which lie 37.4° from the nearest axes, beyond the 34°
    /// inscribed half field of view).
    pub weighted: Vec<f32>,
    /// Population standard deviation, 0 with one sample (with [`Extras::spread`]).
    pub spread: Vec<f32>,
}

/// What [`RowStats`] computes beyond the mean and the weighted mean.
#[derive(Debug, Default, Clone, Copy)]
pub(crate) struct Extras {
    /// The nearest valid face's sample (needs ranks).
    pub nearest: bool,
    /// The spread.
    pub spread: bool,
}

impl RowStats {
    /// Start a row `width` pixels wide.
    pub(crate) fn start(&mut self, width: usize, extras: Extras) {
        let reset = |v: &mut Vec<f32>, x: f32| {
            v.clear();
            v.resize(width, x);
        };
        self.extras = extras;
        reset(&mut self.count, 0.0);
        reset(&mut self.shifted_sum, 0.0);
        reset(&mut self.weight_sum, 0.0);
        reset(&mut self.weighted_sum, 0.0);
        // Set by each pixel's first valid sample before it is read.
        self.shift.resize(width, 0.0);
        if extras.spread {
            reset(&mut self.shifted_squares, 0.0);
        }
        if extras.nearest {
            reset(&mut self.nearest, f32::NAN);
            self.rank.clear();
            self.rank.resize(width, u8::MAX);
        }
    }

    /// Add the samples `values` of one run over `columns`, with their blending `weights` (none:
    /// all 1) and nearness `ranks` (read only for [`Extras::nearest`]).
    #[expect(
        clippy::inline_always,
        reason = "per-pixel kernel; inlined it measured faster"
    )]
    #[inline(always)]
    pub(crate) fn add_run(
        &mut self,
        columns: std::ops::Range<usize>,
        values: &[f32],
        weights: Option<&[f32]>,
        ranks: impl Iterator<Item = u8>,
    ) {
        match (weights, self.extras.spread) {
            (Some(w), true) => self.add::<true>(columns.clone(), values, w.iter().copied()),
            (Some(w), false) => self.add::<false>(columns.clone(), values, w.iter().copied()),
            (None, true) => self.add::<true>(columns.clone(), values, std::iter::repeat(1.0)),
            (None, false) => self.add::<false>(columns.clone(), values, std::iter::repeat(1.0)),
        }
        if self.extras.nearest {
            let best = self.rank[columns.clone()]
                .iter_mut()
                .zip(&mut self.nearest[columns]);
            for ((rank, nearest), (&v, r)) in best.zip(values.iter().zip(ranks)) {
                // Branch-free: which face is nearest varies from pixel to pixel.
                #[expect(
                    clippy::needless_bitwise_bool,
                    reason = "branch-free, so the loop vectorises"
                )]
                let nearer = v.is_finite() & (r < *rank);
                *rank = if nearer { r } else { *rank };
                *nearest = if nearer { v } else { *nearest };
            }
        }
    }

    #[expect(
        clippy::inline_always,
        reason = "per-pixel kernel; inlined it measured faster"
    )]
    #[inline(always)]
    fn add<const SPREAD: bool>(
        &mut self,
        columns: std::ops::Range<usize>,
        values: &[f32],
        weights: impl Iterator<Item = f32>,
    ) {
        let sums = self.count[columns.clone()]
            .iter_mut()
            .zip(&mut self.shift[columns.clone()])
            .zip(&mut self.shifted_sum[columns.clone()])
            .zip(&mut self.weight_sum[columns.clone()])
            .zip(&mut self.weighted_sum[columns.clone()]);
        let mut squares = if SPREAD {
            self.shifted_squares[columns].iter_mut()
        } else {
            [].iter_mut()
        };
        // Branch-free, so it vectorises: an invalid sample adds zeros.
        for (((((n, shift), sum), wsum), wv), (&v, w)) in sums.zip(values.iter().zip(weights)) {
            let ok = v.is_finite();
            #[expect(
                clippy::needless_bitwise_bool,
                reason = "branch-free, so the loop vectorises"
            )]
            let first = ok & (*n == 0.0);
            *shift = if first { v } else { *shift };
            let d = if ok { v - *shift } else { 0.0 };
            let (v, w) = if ok { (v, w) } else { (0.0, 0.0) };
            *n += f32::from(u8::from(ok));
            *sum += d;
            *wsum += w;
            *wv += w * v;
            if SPREAD {
                if let Some(sq) = squares.next() {
                    *sq += d * d;
                }
            }
        }
    }

    /// The per-pixel results, once every run is added.
    pub(crate) fn finish(&mut self) {
        let width = self.count.len();
        for v in [&mut self.mean, &mut self.weighted] {
            v.clear();
            v.resize(width, f32::NAN);
        }
        let sums = self.count.iter().zip(&self.shift).zip(&self.shifted_sum);
        let weighted = self.weight_sum.iter().zip(&self.weighted_sum);
        let outs = self.mean.iter_mut().zip(self.weighted.iter_mut());
        for ((((&n, &shift), &sum), (&wsum, &wv)), (mean, weighted)) in sums.zip(weighted).zip(outs)
        {
            if n > 0.0 {
                *mean = shift + sum / n;
                *weighted = if wsum > 0.0 { wv / wsum } else { *mean };
            }
        }
        if self.extras.spread {
            self.spread.clear();
            let parts = self
                .count
                .iter()
                .zip(&self.shifted_sum)
                .zip(&self.shifted_squares);
            self.spread.extend(parts.map(|((&n, &sum), &squares)| {
                let mean = sum / n; // NaN where no sample
                (squares / n - mean * mean).max(0.0).sqrt()
            }));
        }
    }

    /// The statistics of a whole row of samples.
    pub(crate) fn compute(&mut self, row: &RowSamples, width: usize, spread: bool) {
        let nearest = !row.ranks.is_empty();
        self.start(width, Extras { nearest, spread });
        let weights = (!row.weights.is_empty()).then_some(&row.weights[..]);
        for run in &row.runs {
            let ranks = row.ranks.get(run.taps()).unwrap_or_default();
            self.add_run(
                run.columns(),
                &row.values[run.taps()],
                weights.map(|w| &w[run.taps()]),
                ranks.iter().copied(),
            );
        }
        self.finish();
    }
}

/// Which statistic of the valid samples a blend outputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Statistic {
    Nearest,
    Mean,
    Weighted,
}

impl RowStats {
    fn get(&self, which: Statistic) -> &[f32] {
        match which {
            Statistic::Nearest => &self.nearest,
            Statistic::Mean => &self.mean,
            Statistic::Weighted => &self.weighted,
        }
    }
}

/// Blend every ERP row of per-tangent maps (N·h·w, NaN = invalid) into `disparity` (H·W) with
/// the statistic `which` of the valid samples, and their spread into `spread` (H·W) if given.
///
/// # Panics
/// If the outputs are not H·W long, or `tangents` or `weights` do not belong to `taps`.
pub(crate) fn blend_rows(
    taps: &ErpTaps,
    layout: &Layout,
    tangents: &[f32],
    weights: Option<&WeightMaps>,
    which: Statistic,
    disparity: &mut [f32],
    spread: Option<&mut [f32]>,
) {
    let ew = layout.erp_width;
    assert!(disparity.len() == layout.erp_height * ew);
    assert!(spread.as_ref().is_none_or(|s| s.len() == disparity.len()));
    disparity
        .par_chunks_mut(ew)
        .zip(optional_chunks(spread, ew, layout.erp_height))
        .enumerate()
        .for_each_init(
            || (Vec::new(), Vec::new(), RowStats::default()),
            |(buffer, weight_buffer, stats), (i, (out, out_spread))| {
                let nearest = which == Statistic::Nearest;
                // One face's value alone cannot place an edge between its pixels: across one,
                // its side is wrong a quarter of the time, which costs more than the bilinear
                // mix (docs/method.md, "Sampling across depth edges"). Several faces can.
                let sampling = if nearest {
                    Sampling::Bilinear
                } else {
                    Sampling::DepthEdges
                };
                let spread = out_spread.is_some();
                stats.start(ew, Extras { nearest, spread });
                // Values and weights sampled together: each tap is decoded once.
                match weights {
                    Some(w) => taps.sample_runs_many(
                        [tangents, w.maps()],
                        sampling,
                        i,
                        [buffer, weight_buffer],
                        |run, [values, weights], ranks| {
                            stats.add_run(run.columns(), values, Some(weights), ranks);
                        },
                    ),
                    None => {
                        taps.sample_runs(tangents, sampling, i, buffer, |run, values, ranks| {
                            stats.add_run(run.columns(), values, None, ranks);
                        });
                    }
                }
                stats.finish();
                out.copy_from_slice(stats.get(which));
                if let Some(out_spread) = out_spread {
                    out_spread.copy_from_slice(&stats.spread);
                }
            },
        );
}

/// `count` chunks of `size` of `data`, or `count` Nones: an output that may be skipped, to zip
/// with the chunks of one that may not.
pub(crate) fn optional_chunks(
    data: Option<&mut [f32]>,
    size: usize,
    count: usize,
) -> rayon::vec::IntoIter<Option<&mut [f32]>> {
    let chunks: Vec<Option<&mut [f32]>> = match data {
        Some(d) => d.chunks_mut(size).map(Some).collect(),
        None => (0..count).map(|_| None).collect(),
    };
    chunks.into_par_iter()
}

/// Weighted blend of per-tangent maps (N·h·w, NaN = invalid) with per-face `weights` (sampled
/// at the taps): `disparity` (H·W) gets Σ w·v / Σ w over the valid
/// samples (see `RowStats::weighted` for the fall-back), `spread` (H·W, if given) the
/// population standard deviation of the valid samples.
///
/// # Panics
/// If the outputs are not H·W long.
pub fn weighted_blend(
    taps: &ErpTaps,
    layout: &Layout,
    tangents: &[f32],
    weights: &WeightMaps,
    disparity: &mut [f32],
    spread: Option<&mut [f32]>,
) {
    let which = Statistic::Weighted;
    blend_rows(
        taps,
        layout,
        tangents,
        Some(weights),
        which,
        disparity,
        spread,
    );
}

/// Unweighted mean of per-tangent maps (N·h·w, NaN = invalid): `disparity` (H·W) gets the mean
/// of the valid samples, NaN where there is none; `spread` (H·W, if given) their population
/// standard deviation (0 with one sample, NaN with none).
///
/// # Panics
/// If the outputs are not H·W long.
pub fn mean_blend(
    taps: &ErpTaps,
    layout: &Layout,
    tangents: &[f32],
    disparity: &mut [f32],
    spread: Option<&mut [f32]>,
) {
    blend_rows(
        taps,
        layout,
        tangents,
        None,
        Statistic::Mean,
        disparity,
        spread,
    );
}

/// Nearest-face blend of per-tangent maps (N·h·w, NaN = invalid): `disparity` (H·W) gets the
/// valid sample of the face whose axis is nearest the pixel (for the icosahedron: the face whose
/// un-padded triangle contains it, falling back to the next nearest where that face has no valid
/// sample); `spread` as in [`mean_blend`].
///
/// # Panics
/// If the outputs are not H·W long.
pub fn nearest_blend(
    taps: &ErpTaps,
    layout: &Layout,
    tangents: &[f32],
    disparity: &mut [f32],
    spread: Option<&mut [f32]>,
) {
    blend_rows(
        taps,
        layout,
        tangents,
        None,
        Statistic::Nearest,
        disparity,
        spread,
    );
}

/// Reweighting rounds of the consensus blend: measured on synthetic rooms with content errors,
/// the consensus moves by less than 1e-3 of the disparity after the third.
pub const CONSENSUS_ROUNDS: usize = 3;
/// Cauchy constant of the consensus blend, in units of the residual scale σ (95 % efficiency
/// on gaussian disagreement).
const CONSENSUS_CAUCHY: f32 = 2.385;
/// Every how many taps one enters the estimate of σ (a median over a regular subsample).
const SCALE_STRIDE: usize = 4;
/// ERP rows the estimate of σ reads (evenly spaced; all rows of smaller maps): a fixed budget,
/// so that the extra pass costs the same at every resolution (at 8K it was a third of the
/// blend's time when it read every row).
const SCALE_ROWS: usize = 256;

/// Per column of a row, the sums over its samples of `term(value, prior weight, estimate)` =
/// (numerator, denominator) into `num` and `den`, with `at` the current estimate per column.
/// Branch-free: `term` sees invalid (non-finite) samples too and must add zeros for them.
fn accumulate_row(
    row: &RowSamples,
    at: &[f32],
    num: &mut [f32],
    den: &mut [f32],
    term: impl Fn(f32, f32, f32) -> (f32, f32),
) {
    num.fill(0.0);
    den.fill(0.0);
    for run in &row.runs {
        let (taps, cols) = (run.taps(), run.columns());
        let len = taps.len();
        let (values, weights) = (&row.values[taps.clone()], &row.weights[taps]);
        let (at, num, den) = (
            &at[cols.clone()][..len],
            &mut num[cols.clone()][..len],
            &mut den[cols][..len],
        );
        let samples = values.iter().zip(weights).zip(at);
        for ((n, d), ((&v, &p), &m)) in num.iter_mut().zip(den.iter_mut()).zip(samples) {
            let (a, b) = term(v, p, m);
            *n += a;
            *d += b;
        }
    }
}

/// Disagreement-aware blend: per ERP pixel, an iteratively reweighted mean of the valid samples
/// with the per-face `weights` (at the taps) as prior, each sample's weight multiplied by the
/// Cauchy weight 1/(1 + (e/c)²) of its distance e from the current consensus (c = 2.385·σ,
/// σ = 1.4826 × the median distance of a sample from its pixel's prior-weighted mean, over a
/// regular subsample of the pixels at least two faces see), [`CONSENSUS_ROUNDS`] times from the
/// prior-weighted mean. A face that disagrees with the others where three or more see a pixel
/// loses its say there.
///
/// `disparity` (H·W) gets the consensus, NaN where no face has a valid sample. `confidence`
/// (H·W, if given) the disagreement left: √(Σ p·e²/(1 + (e/c)²) / Σ p) with p the prior
/// weights and e the distance from the consensus, in disparity units (0 with one sample, NaN
/// with none). An outlier's term is bounded by c², so a face that was voted down still marks its
/// footprint, without one wild value swamping the map. Returns σ.
///
/// # Panics
/// If the outputs are not H·W long.
pub fn consensus_blend(
    taps: &ErpTaps,
    layout: &Layout,
    tangents: &[f32],
    weights: &WeightMaps,
    disparity: &mut [f32],
    confidence: Option<&mut [f32]>,
) -> f32 {
    consensus_blend_with_prior(taps, layout, tangents, weights, None, disparity, confidence)
}

/// The global prior's vote in [`consensus_blend_with_prior`] (docs/method.md, "Global prior"):
/// the prior map and the affine map that puts it in the tangents' units (the alignment's fit).
#[derive(Debug, Clone, Copy)]
pub struct PriorVote<'a> {
    /// The prior (any ERP resolution, NaN = unknown, with its confidence).
    pub prior: &'a Prior,
    /// The prior P in the tangents' units is `scale`·P + `offset`.
    pub scale: f64,
    /// See `scale`.
    pub offset: f64,
}

impl PriorVote<'_> {
    /// The bilinear taps along a row of an `ew`-column ERP grid: per column, the prior's two
    /// columns (wrapping in longitude) and the second one's weight.
    fn columns(&self, ew: usize) -> Vec<(u32, u32, f32)> {
        let wp = self.prior.width;
        let step = wp as f64 / ew as f64;
        (0..ew)
            .map(|j| {
                let col = ((j as f64 + 0.5) * step - 0.5).rem_euclid(wp as f64);
                let c0 = (col as usize).min(wp - 1);
                (c0 as u32, ((c0 + 1) % wp) as u32, (col - c0 as f64) as f32)
            })
            .collect()
    }

    /// Row `i` of an `eh`-row ERP grid with the column taps `columns`: the prior in the
    /// tangents' units (bilinear, NaN where a tap is unknown) into `value`, its confidence (0
    /// where unknown) into `trust`. The two prior rows resampled along the row are kept in
    /// `cache` for the next ERP rows between the same prior rows (8 per prior row at 8K from a
    /// 512-row prior): the same numbers, one gather per prior row instead of per ERP row.
    fn row(
        &self,
        i: usize,
        eh: usize,
        columns: &[(u32, u32, f32)],
        cache: &mut PriorRows,
        value: &mut Vec<f32>,
        trust: &mut Vec<f32>,
    ) {
        let p = self.prior;
        let (hp, wp) = (p.height, p.width);
        let row = ((i as f64 + 0.5) * hp as f64 / eh as f64 - 0.5).clamp(0.0, (hp - 1) as f64);
        let r0 = (row as usize).min(hp - 2);
        let fy = (row - r0 as f64) as f32;
        if cache.row != Some(r0) {
            let along = |a: &[f32], out: &mut Vec<f32>| {
                out.clear();
                out.extend(columns.iter().map(|&(c0, c1, fx)| {
                    let (a0, a1) = (a[c0 as usize], a[c1 as usize]);
                    a0 + fx * (a1 - a0)
                }));
            };
            along(&p.values[r0 * wp..][..wp], &mut cache.top);
            along(&p.values[(r0 + 1) * wp..][..wp], &mut cache.bottom);
            if let Some(c) = &p.confidence {
                along(&c[r0 * wp..][..wp], &mut cache.confidence_top);
                along(&c[(r0 + 1) * wp..][..wp], &mut cache.confidence_bottom);
            }
            cache.row = Some(r0);
        }
        let (scale, offset) = (self.scale as f32, self.offset as f32);
        value.clear();
        value.extend(
            cache
                .top
                .iter()
                .zip(&cache.bottom)
                .map(|(&t, &b)| scale * (t + fy * (b - t)) + offset), // NaN when a tap is
        );
        trust.clear();
        match &p.confidence {
            None => trust.extend(value.iter().map(|v| f32::from(u8::from(v.is_finite())))),
            Some(_) => trust.extend(
                cache
                    .confidence_top
                    .iter()
                    .zip(&cache.confidence_bottom)
                    .zip(value.iter())
                    .map(|((&t, &b), v)| if v.is_finite() { t + fy * (b - t) } else { 0.0 }),
            ),
        }
    }
}

/// `confidence` (H·W of an `ew`-column ERP grid) combined with the prior's disagreement with
/// `disparity`, root sum of squares: c ← √(c² + (d − P)²), with P the vote's prior in the
/// result's units read as the vote reads it (bilinear, wrapping in longitude). Where P or d is
/// unknown the confidence is kept; where it is NaN it stays NaN (docs/method.md, "Global
/// prior"). One pass over the rows: as numpy array operations this was 0.5 s at 8K.
///
/// # Panics
/// If `confidence` and `disparity` differ in length or are not whole rows of `ew`.
pub fn combine_confidence_with_prior(
    vote: &PriorVote<'_>,
    disparity: &[f32],
    confidence: &mut [f32],
    ew: usize,
) {
    assert!(ew > 0 && disparity.len() == confidence.len() && disparity.len().is_multiple_of(ew));
    let eh = disparity.len() / ew;
    let columns = vote.columns(ew);
    confidence
        .par_chunks_mut(ew)
        .zip(disparity.par_chunks(ew))
        .enumerate()
        .for_each_init(
            || (PriorRows::default(), Vec::new(), Vec::new()),
            |(cache, value, trust), (i, (conf, row))| {
                vote.row(i, eh, &columns, cache, value, trust);
                for ((c, &d), &p) in conf.iter_mut().zip(row).zip(value.iter()) {
                    let gap = (d - p).abs();
                    let gap = if gap.is_nan() { 0.0 } else { gap };
                    *c = (gap * gap + *c * *c).sqrt();
                }
            },
        );
}

/// A thread's last two prior rows resampled along an ERP row ([`PriorVote::row`]).
#[derive(Debug, Default)]
struct PriorRows {
    /// The upper prior row they come from (None: nothing kept yet).
    row: Option<usize>,
    top: Vec<f32>,
    bottom: Vec<f32>,
    confidence_top: Vec<f32>,
    confidence_bottom: Vec<f32>,
}

/// The prior's vote scale c_P, in units of the robust scale of the distance between the
/// prior and the tangents' weighted mean (1.4826 × its median): of 0.5, 1 and 2, measured on
/// two synthetic rooms at 2K with content errors and with a wrong prior (benches/bench_prior.py,
/// docs/method.md), 1 was within 2 % of the best in both.
const PRIOR_VOTE_SCALE: f32 = 1.0;
/// The prior's trust at a pixel is the Cauchy weight of its distance from the nearest face, at
/// this many c_P: a prior that no face agrees with (a window, a mirror, a wrong region) does
/// not vote there.
const PRIOR_TRUST_SCALE: f32 = 2.0;

/// The least factor the prior's vote gives a face: its Cauchy weight times the consensus
/// rounds' would otherwise reach subnormal floats, whose arithmetic made the blend 5x slower.
const MIN_PRIOR_VOTE: f32 = 1e-3;

/// Multiply each valid sample's weight of `row` by its agreement with the prior:
/// (1 − t) + t/(1 + ((v − P)/c_P)²), with t the prior's trust at the pixel (its confidence
/// times the Cauchy weight of the nearest sample's distance at [`PRIOR_TRUST_SCALE`] c_P).
/// Only the weights change: the consensus is still a mean of the faces' own values, so the
/// prior picks among the faces where they disagree and never blurs their detail.
pub(super) fn prior_vote(
    row: &mut RowSamples,
    prior: &[f32],
    trust: &mut [f32],
    nearest: &mut [f32],
    inv_c: f32,
) {
    // The same element-wise operations 8 lanes wide where the CPU has AVX2 (no FMA, no
    // reduction across lanes): the same bits as the baseline build's 4 lanes (tested), with
    // half the instructions. With SSE2 alone the vote was a tenth of an 8K blend's time.
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { prior_vote_avx2(row, prior, trust, nearest, inv_c) };
        return;
    }
    prior_vote_lanes(row, prior, trust, nearest, inv_c);
}

/// [`prior_vote`] compiled for AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn prior_vote_avx2(
    row: &mut RowSamples,
    prior: &[f32],
    trust: &mut [f32],
    nearest: &mut [f32],
    inv_c: f32,
) {
    prior_vote_lanes(row, prior, trust, nearest, inv_c);
}

/// The body of [`prior_vote`], inlined into each target's version.
#[expect(
    clippy::inline_always,
    reason = "must inline into prior_vote_avx2 to be compiled for AVX2"
)]
#[inline(always)]
pub(super) fn prior_vote_lanes(
    row: &mut RowSamples,
    prior: &[f32],
    trust: &mut [f32],
    nearest: &mut [f32],
    inv_c: f32,
) {
    // Branch-free over each run's columns (contiguous), so the loops vectorise: a sample with
    // no finite distance (its value or the prior unknown) counts as infinitely far for the
    // nearest, and as distance 0, given the factor (1 − t) + t = 1, in the weights (t is 0
    // where the prior is unknown; an invalid sample's weight is not read by the blend). The
    // nearest sample's Cauchy weight is that of the least squared distance (1/(1 + x) is
    // monotonic in floating point too): one division per column, not one per sample.
    nearest.fill(f32::INFINITY);
    for run in &row.runs {
        let cols = run.columns();
        let values = &row.values[run.taps()];
        let near = &mut nearest[cols.clone()];
        for ((&v, &p), n) in values.iter().zip(&prior[cols]).zip(near.iter_mut()) {
            let e = (v - p) * inv_c * (1.0 / PRIOR_TRUST_SCALE);
            let e2 = if e.is_finite() { e * e } else { f32::INFINITY };
            *n = n.min(e2);
        }
    }
    for (t, &n) in trust.iter_mut().zip(nearest.iter()) {
        *t *= 1.0 / (1.0 + n);
    }
    for run in &row.runs {
        let cols = run.columns();
        let taps = run.taps();
        let (values, weights) = (&row.values[taps.clone()], &mut row.weights[taps]);
        let (prior, trust) = (&prior[cols.clone()], &trust[cols]);
        for (((&v, w), &p), &t) in values.iter().zip(weights.iter_mut()).zip(prior).zip(trust) {
            let e = (v - p) * inv_c;
            let e = if e.is_finite() { e } else { 0.0 };
            *w *= ((1.0 - t) + t / (1.0 + e * e)).max(MIN_PRIOR_VOTE);
        }
    }
}

/// The distances the consensus blend's scales come from, over a regular subsample (thread-count
/// independent: rows in parallel, concatenated in row order): of each sample from its pixel's
/// weighted mean where two or more faces see it (σ), and of the weighted mean from the prior
/// (its vote's scale; empty without a prior).
fn consensus_distances(
    taps: &ErpTaps,
    tangents: &[f32],
    weights: &WeightMaps,
    prior: Option<&PriorVote<'_>>,
    prior_columns: &[(u32, u32, f32)],
    eh: usize,
    ew: usize,
) -> (Vec<f32>, Vec<f32>) {
    let row_stride = (eh / SCALE_ROWS).max(1);
    let distances: Vec<(Vec<f32>, Vec<f32>)> = (0..eh)
        .into_par_iter()
        .step_by(row_stride)
        .map_init(
            || {
                (
                    RowSamples::default(),
                    RowStats::default(),
                    PriorRows::default(),
                    (Vec::new(), Vec::new()),
                )
            },
            |(row, stats, cache, (prior_row, trust_row)), i| {
                row.fill_from_taps(taps, tangents, Some(weights), false, i);
                stats.compute(row, ew, false);
                let mut out = Vec::new();
                let mut from_prior = Vec::new();
                if let Some(vote) = prior {
                    vote.row(i, eh, prior_columns, cache, prior_row, trust_row);
                    for (j, (&m, &p)) in stats.weighted.iter().zip(prior_row.iter()).enumerate() {
                        let d = (m - p).abs();
                        if j.is_multiple_of(SCALE_STRIDE) && d.is_finite() {
                            from_prior.push(d);
                        }
                    }
                }
                for run in &row.runs {
                    let values = &row.values[run.taps()];
                    let cols = run.columns();
                    for (k, (&v, j)) in values.iter().zip(cols).enumerate() {
                        let seen_twice = stats.count[j] >= 2.0;
                        if (run.start_tap as usize + k).is_multiple_of(SCALE_STRIDE)
                            && seen_twice
                            && v.is_finite()
                        {
                            out.push((v - stats.weighted[j]).abs());
                        }
                    }
                }
                (out, from_prior)
            },
        )
        .collect();
    distances
        .into_iter()
        .fold((Vec::new(), Vec::new()), |(mut a, mut b), (x, y)| {
            a.extend(x);
            b.extend(y);
            (a, b)
        })
}

/// [`consensus_blend`] with the global prior's vote, if any (`prior_vote`): where the faces
/// disagree, those nearer the prior (where it is trusted) weigh more from the first estimate
/// on.
///
/// # Panics
/// If the outputs are not H·W long.
pub fn consensus_blend_with_prior(
    taps: &ErpTaps,
    layout: &Layout,
    tangents: &[f32],
    weights: &WeightMaps,
    prior: Option<&PriorVote<'_>>,
    disparity: &mut [f32],
    confidence: Option<&mut [f32]>,
) -> f32 {
    let (eh, ew) = (layout.erp_height, layout.erp_width);
    assert!(disparity.len() == eh * ew);
    assert!(confidence
        .as_ref()
        .is_none_or(|s| s.len() == disparity.len()));
    let prior_columns = prior.map_or_else(Vec::new, |vote| vote.columns(ew));
    let (mut all, mut from_prior) =
        consensus_distances(taps, tangents, weights, prior, &prior_columns, eh, ew);
    let sigma = robust_scale(&mut all).unwrap_or(1.0);
    let inv_c = 1.0 / (CONSENSUS_CAUCHY * sigma);
    // The prior votes only where its scale is known (some pixel where both are finite).
    let prior = prior.zip(robust_scale(&mut from_prior));
    let inv_c_prior = prior.map_or(0.0, |(_, s)| 1.0 / (PRIOR_VOTE_SCALE * s));
    disparity
        .par_chunks_mut(ew)
        .zip(optional_chunks(confidence, ew, eh))
        .enumerate()
        .for_each_init(
            || {
                (
                    RowSamples::default(),
                    RowStats::default(),
                    vec![0.0f32; ew],
                    vec![0.0f32; ew],
                    (
                        Vec::new(),
                        Vec::new(),
                        vec![0.0f32; ew],
                        PriorRows::default(),
                    ),
                )
            },
            |(row, stats, num, den, (prior_row, trust_row, nearest, cache)),
             (i, (out, out_confidence))| {
                row.fill_from_taps(taps, tangents, Some(weights), false, i);
                if let Some((vote, _)) = prior {
                    vote.row(i, eh, &prior_columns, cache, prior_row, trust_row);
                    prior_vote(row, prior_row, trust_row, nearest, inv_c_prior);
                }
                stats.compute(row, ew, false);
                out.copy_from_slice(&stats.weighted);
                for _ in 0..CONSENSUS_ROUNDS {
                    accumulate_row(row, out, num, den, |v, p, m| {
                        // Computed for every sample and multiplied by 0 or 1: with a select of
                        // 0 instead, the compiler branched around the division for invalid
                        // samples, and the loop did not vectorise. An invalid sample stands in
                        // as the estimate itself (e = 0, r = p), finite wherever the pixel has
                        // a valid sample.
                        let ok = v.is_finite();
                        let v = if ok { v } else { m };
                        let e = (v - m) * inv_c;
                        let r = p / (1.0 + e * e) * f32::from(u8::from(ok));
                        (r * v, r)
                    });
                    for ((m, &n), &d) in out.iter_mut().zip(num.iter()).zip(den.iter()) {
                        *m = if d > 0.0 { n / d } else { *m };
                    }
                }
                if let Some(conf) = out_confidence {
                    accumulate_row(row, out, num, den, |v, p, m| {
                        // As in the rounds: no select around the division.
                        let ok = v.is_finite();
                        let e = if ok { v } else { m } - m;
                        let u = e * inv_c;
                        // Unweighted (p = 1) where the prior weighs every sample 0.
                        let p = p.max(1e-6) * f32::from(u8::from(ok));
                        (p * e * e / (1.0 + u * u), p)
                    });
                    for ((c, &n), &d) in conf.iter_mut().zip(num.iter()).zip(den.iter()) {
                        *c = (n / d).sqrt(); // NaN where no sample (0/0)
                    }
                }
            },
        );
    sigma
}

/// 1.4826 × the median of `distances` (reordered), at least the smallest positive f32; None
/// when there are none.
fn robust_scale(distances: &mut [f32]) -> Option<f32> {
    if distances.is_empty() {
        return None;
    }
    let mid = distances.len() / 2;
    let (_, &mut median, _) = distances.select_nth_unstable_by(mid, f32::total_cmp);
    Some((1.4826 * median).max(f32::MIN_POSITIVE))
}

/// Fewest valid samples at a pixel for [`median_blend`] to take their weighted median (below it
/// the weighted mean: with two samples a median cannot tell which one is wrong).
pub const MEDIAN_MIN_SAMPLES: f32 = 3.0;

/// Per column of a row whose statistics `stats` are computed, the prior-weighted median of its
/// valid samples where at least [`MEDIAN_MIN_SAMPLES`] see it, into `out` (other columns are
/// left as they are). The weighted median is the smallest sample whose cumulative weight, in
/// increasing order of value, reaches half the total; with a total weight of 0 the samples
/// count equally. `scratch` holds the per-column samples (reused between rows).
fn row_weighted_median(
    row: &RowSamples,
    stats: &RowStats,
    out: &mut [f32],
    scratch: &mut (Vec<usize>, Vec<(f32, f32)>),
) {
    let (starts, samples) = scratch;
    // Counting sort of the valid samples by column: a pixel's samples come from several runs.
    starts.clear();
    let mut total = 0usize;
    for &n in &stats.count {
        starts.push(total);
        total += n as usize;
    }
    samples.clear();
    samples.resize(total, (0.0, 0.0));
    let mut fill = starts.clone();
    for run in &row.runs {
        let values = &row.values[run.taps()];
        let weights = &row.weights[run.taps()];
        for ((&v, &w), j) in values.iter().zip(weights).zip(run.columns()) {
            if v.is_finite() {
                samples[fill[j]] = (v, w);
                fill[j] += 1;
            }
        }
    }
    for (j, m) in out.iter_mut().enumerate() {
        if stats.count[j] < MEDIAN_MIN_SAMPLES {
            continue;
        }
        let pixel = &mut samples[starts[j]..fill[j]];
        pixel.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        let weight: f32 = pixel.iter().map(|s| s.1).sum();
        let equal = weight <= 0.0;
        let half = if equal { pixel.len() as f32 } else { weight } / 2.0;
        let mut cumulative = 0.0;
        for &(v, w) in pixel.iter() {
            cumulative += if equal { 1.0 } else { w };
            if cumulative >= half {
                *m = v;
                break;
            }
        }
    }
}

/// Weighted-median blend: per ERP pixel seen by at least [`MEDIAN_MIN_SAMPLES`] valid samples,
/// the median of the samples weighted by the per-face `weights` (at the taps; see
/// `row_weighted_median`); elsewhere the weighted mean, as [`weighted_blend`]. `spread` (H·W,
/// if given) the population standard deviation of the valid samples.
///
/// # Panics
/// If the outputs are not H·W long.
pub fn median_blend(
    taps: &ErpTaps,
    layout: &Layout,
    tangents: &[f32],
    weights: &WeightMaps,
    disparity: &mut [f32],
    spread: Option<&mut [f32]>,
) {
    let (eh, ew) = (layout.erp_height, layout.erp_width);
    assert!(disparity.len() == eh * ew);
    assert!(spread.as_ref().is_none_or(|s| s.len() == disparity.len()));
    disparity
        .par_chunks_mut(ew)
        .zip(optional_chunks(spread, ew, eh))
        .enumerate()
        .for_each_init(
            || {
                (
                    RowSamples::default(),
                    RowStats::default(),
                    (Vec::new(), Vec::new()),
                )
            },
            |(row, stats, scratch), (i, (out, out_spread))| {
                row.fill_from_taps(taps, tangents, Some(weights), false, i);
                stats.compute(row, ew, out_spread.is_some());
                out.copy_from_slice(&stats.weighted);
                row_weighted_median(row, stats, out, scratch);
                if let Some(s) = out_spread {
                    s.copy_from_slice(&stats.spread);
                }
            },
        );
}
