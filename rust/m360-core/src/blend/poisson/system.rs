//! The Poisson normal equations, assembled row by row straight from the taps (no ERP-sized
//! per-face stack: reference pitfall B10, docs/reference-pitfalls.md) and applied matrix-free.

use super::cg::{ordered_sum2, CG_ROWS};
use super::Fidelity;
use crate::blend::rows::{optional_chunks, RowSamples, RowStats};
use crate::blend::WeightMaps;
use crate::resample::{ErpTaps, Run};
use rayon::prelude::*;

/// ERP rows per parallel work item of the Poisson assembly: each item re-samples one row above
/// and one below its own, so larger items waste less, smaller ones balance better.
const ROWS_PER_CHUNK: usize = 16;

/// Something that yields the samples of an ERP row, face by face.
pub(crate) trait RowSource: Sync {
    fn fill(&self, i: usize, out: &mut RowSamples);
}

/// Samples through the plan's taps from tangent images.
pub(crate) struct TapSource<'a> {
    pub(crate) taps: &'a ErpTaps,
    pub(crate) tangents: &'a [f32],
    pub(crate) weights: &'a WeightMaps,
    /// Whether the target needs the nearest face.
    pub(crate) ranks: bool,
}

impl RowSource for TapSource<'_> {
    fn fill(&self, i: usize, out: &mut RowSamples) {
        out.fill_from_taps(self.taps, self.tangents, Some(self.weights), self.ranks, i);
    }
}

/// Samples from K maps already on the ERP grid (K·H·W values and weights, NaN = invalid):
/// one full-row run per map, no ranks (the target is given).
pub(crate) struct LayerSource<'a> {
    pub(crate) values: &'a [f32],
    pub(crate) weights: &'a [f32],
    pub(crate) layers: usize,
    pub(crate) height: usize,
    pub(crate) width: usize,
}

impl RowSource for LayerSource<'_> {
    fn fill(&self, i: usize, out: &mut RowSamples) {
        let (plane, w) = (self.height * self.width, self.width);
        out.runs.clear();
        out.values.clear();
        out.weights.clear();
        out.ranks.clear();
        for k in 0..self.layers {
            let row = k * plane + i * w..k * plane + (i + 1) * w;
            out.runs.push(Run {
                face: k as u32,
                start: 0,
                len: w as u32,
                start_tap: (k * w) as u32,
            });
            out.values.extend_from_slice(&self.values[row.clone()]);
            out.weights.extend_from_slice(&self.weights[row]);
        }
    }
}

/// Weight W = Σ ω_a and weighted target gradient G = Σ ω_a·(D_a(q) − D_a(p)) of every edge
/// p → q of one ERP row, over the faces valid at both ends, with ω_a = (ω_a(p) + ω_a(q))/2
/// taken where the forward difference lives, at the edge's midpoint. (Taking ω_a(p) alone
/// would make the operator change when the image is flipped: the poles would no longer be
/// treated alike.)
#[derive(Debug, Default)]
struct RowEdges {
    weight: Vec<f64>,
    gradient: Vec<f64>,
}

impl RowEdges {
    fn reset(&mut self, width: usize) {
        for v in [&mut self.weight, &mut self.gradient] {
            v.clear();
            v.resize(width, 0.0);
        }
    }

    /// Add face term (value p, weight wp) → (value q, weight wq) to the edge at column `j`.
    #[expect(
        clippy::inline_always,
        reason = "per-pixel kernel; inlined it measured faster"
    )]
    #[inline(always)]
    fn add(&mut self, j: usize, (p, wp): (f32, f32), (q, wq): (f32, f32)) {
        if p.is_finite() && q.is_finite() {
            let w = 0.5 * (f64::from(wp) + f64::from(wq));
            self.weight[j] += w;
            self.gradient[j] += w * (f64::from(q) - f64::from(p));
        }
    }

    /// The edges from each pixel of `row` to its right neighbour (column W−1 wraps to 0).
    fn horizontal(&mut self, row: &RowSamples, width: usize) {
        self.reset(width);
        let at = |t: usize| (row.values[t], row.weight(t));
        for run in &row.runs {
            let taps = run.taps();
            for (j, t) in run.columns().zip(taps.clone()).take(taps.len() - 1) {
                self.add(j, at(t), at(t + 1));
            }
            if run.columns().end == width {
                // The run goes on at column 0 of the same row, if the face sees it there.
                let wrap = row.runs.iter().find(|r| r.face == run.face && r.start == 0);
                if let Some(next) = wrap {
                    self.add(width - 1, at(taps.end - 1), at(next.start_tap as usize));
                }
            }
        }
    }

    /// The edges from each pixel of `upper` to the one below it in `lower`.
    fn vertical(&mut self, upper: &RowSamples, lower: &RowSamples, width: usize) {
        self.reset(width);
        for a in &upper.runs {
            for b in lower.runs.iter().filter(|b| b.face == a.face) {
                let (lo, hi) = (a.start.max(b.start), (a.start + a.len).min(b.start + b.len));
                for j in lo..hi {
                    let ta = (a.start_tap + j - a.start) as usize;
                    let tb = (b.start_tap + j - b.start) as usize;
                    self.add(
                        j as usize,
                        (upper.values[ta], upper.weight(ta)),
                        (lower.values[tb], lower.weight(tb)),
                    );
                }
            }
        }
    }
}

fn target_of(stats: &RowStats, j: usize, fidelity: Fidelity) -> f64 {
    f64::from(match fidelity {
        Fidelity::Nearest => stats.nearest[j],
        // Consensus is given as an image by the caller (Target::Given); frustum stands in.
        Fidelity::Frustum | Fidelity::Consensus => stats.weighted[j],
        Fidelity::Mean => stats.mean[j],
    })
}

/// The assembled normal equations (λ_p I + L_W) x = λ_p t + div G on an H×W ERP grid.
///
/// L_W is the weighted graph Laplacian of the ERP 4-neighbour grid: horizontal edges wrap in
/// longitude (column W−1 → 0), vertical edges join rows i and i+1 and never cross a pole, so
/// rows 0 and H−1 are treated alike (reference pitfall B7 in docs/reference-pitfalls.md: a Dirichlet row below the
/// bottom only).
/// Pixels no face sees get the decoupled equation x = 0 and become NaN.
#[derive(Debug)]
pub(crate) struct System {
    pub(crate) height: usize,
    pub(crate) width: usize,
    /// Weight of the edge from each pixel to its right neighbour (wrapping).
    pub(crate) right: Vec<f32>,
    /// Weight of the edge from each pixel to the one below (0 on the last row).
    pub(crate) down: Vec<f32>,
    /// Diagonal λ_p + Σ incident edge weights (1 at unseen pixels).
    pub(crate) diag: Vec<f64>,
    /// Right-hand side.
    pub(crate) rhs: Vec<f64>,
    /// Fidelity target, NaN at unseen pixels.
    pub(crate) target: Vec<f64>,
}

/// Where the fidelity target comes from.
#[derive(Clone, Copy)]
pub(crate) enum Target<'a> {
    /// Computed from each pixel's samples.
    FromSamples(Fidelity),
    /// Given on the ERP grid (H·W, NaN = none).
    Given(&'a [f32]),
}

pub(crate) fn assemble(
    source: &dyn RowSource,
    height: usize,
    width: usize,
    lambda: f64,
    target_spec: Target<'_>,
    spread: Option<&mut [f32]>,
) -> System {
    let n = height * width;
    let mut right = vec![0.0f32; n];
    let mut down = vec![0.0f32; n];
    let mut rhs = vec![0.0f64; n];
    let mut target = vec![0.0f64; n];
    let chunk = ROWS_PER_CHUNK * width;
    right
        .par_chunks_mut(chunk)
        .zip(down.par_chunks_mut(chunk))
        .zip(rhs.par_chunks_mut(chunk))
        .zip(target.par_chunks_mut(chunk))
        .zip(optional_chunks(
            spread,
            chunk,
            height.div_ceil(ROWS_PER_CHUNK),
        ))
        .enumerate()
        .for_each(|(c, ((((right, down), div), target), mut spread))| {
            let i0 = c * ROWS_PER_CHUNK;
            let rows = right.len() / width;
            let (mut cur, mut next) = (RowSamples::default(), RowSamples::default());
            let mut stats = RowStats::default();
            let (mut across, mut below, mut above) = (
                RowEdges::default(),
                RowEdges::default(),
                RowEdges::default(),
            );
            source.fill(i0, &mut cur);
            // Edges entering this row from above (none on row 0).
            above.reset(width);
            if i0 > 0 {
                let mut prev = RowSamples::default();
                source.fill(i0 - 1, &mut prev);
                above.vertical(&prev, &cur, width);
            }
            for r in 0..rows {
                let i = i0 + r;
                across.horizontal(&cur, width);
                if i + 1 < height {
                    source.fill(i + 1, &mut next);
                    below.vertical(&cur, &next, width);
                } else {
                    below.reset(width);
                }
                stats.compute(&cur, width, spread.is_some());
                let row = r * width..(r + 1) * width;
                let (right, down) = (&mut right[row.clone()], &mut down[row.clone()]);
                let (div, target) = (&mut div[row.clone()], &mut target[row.clone()]);
                if let Some(spread) = spread.as_deref_mut() {
                    spread[row.clone()].copy_from_slice(&stats.spread);
                }
                for j in 0..width {
                    right[j] = across.weight[j] as f32;
                    down[j] = below.weight[j] as f32;
                    target[j] = match target_spec {
                        Target::FromSamples(f) => target_of(&stats, j, f),
                        Target::Given(t) => f64::from(t[i * width + j]),
                    };
                    let left = (j + width - 1) % width;
                    div[j] = across.gradient[left] - across.gradient[j] + above.gradient[j]
                        - below.gradient[j];
                }
                std::mem::swap(&mut above, &mut below);
                std::mem::swap(&mut cur, &mut next);
            }
        });
    // diag and rhs need the left and upper neighbours' edges: a second, cheap pass.
    let mut diag = vec![0.0f64; n];
    diag.par_chunks_mut(width)
        .zip(rhs.par_chunks_mut(width))
        .enumerate()
        .for_each(|(i, (diag, rhs))| {
            let base = i * width;
            for j in 0..width {
                let p = base + j;
                let t = target[p];
                if !t.is_finite() {
                    diag[j] = 1.0;
                    rhs[j] = 0.0;
                    continue;
                }
                let left = base + (j + width - 1) % width;
                let mut d =
                    lambda + f64::from(right[p]) + f64::from(right[left]) + f64::from(down[p]);
                if i > 0 {
                    d += f64::from(down[p - width]);
                }
                diag[j] = d;
                rhs[j] += lambda * t;
            }
        });
    System {
        height,
        width,
        right,
        down,
        diag,
        rhs,
        target,
    }
}

impl System {
    /// y = A x, parallel over rows (each y element written once: deterministic).
    pub(crate) fn apply(&self, x: &[f64], y: &mut [f64]) {
        let w = self.width;
        y.par_chunks_mut(CG_ROWS * w)
            .enumerate()
            .for_each(|(c, y)| {
                self.apply_rows(x, y, c * CG_ROWS);
            });
    }

    /// Rows `i0..` of y = A x into `y` (whole rows); returns the partial sum of x·y over them.
    /// Whole-row slices with the longitude wrap peeled off, so the loops vectorise.
    #[inline]
    pub(crate) fn apply_rows(&self, x: &[f64], y: &mut [f64], i0: usize) -> f64 {
        let (h, w) = (self.height, self.width);
        let mut dot = 0.0;
        for (r, y) in y.chunks_mut(w).enumerate() {
            let i = i0 + r;
            let row = i * w..(i + 1) * w;
            let (right, diag, xr) = (&self.right[row.clone()], &self.diag[row.clone()], &x[row]);
            if w < 3 {
                for j in 0..w {
                    let (l, rr) = ((j + w - 1) % w, (j + 1) % w);
                    y[j] = diag[j] * xr[j]
                        - f64::from(right[j]) * xr[rr]
                        - f64::from(right[l]) * xr[l];
                }
            } else {
                y[0] = diag[0] * xr[0]
                    - f64::from(right[0]) * xr[1]
                    - f64::from(right[w - 1]) * xr[w - 1];
                for (((y, (d, xc)), (r, rl)), (xl, xn)) in y[1..w - 1]
                    .iter_mut()
                    .zip(diag[1..w - 1].iter().zip(&xr[1..w - 1]))
                    .zip(right[1..w - 1].iter().zip(&right[..w - 2]))
                    .zip(xr[..w - 2].iter().zip(&xr[2..]))
                {
                    *y = d * xc - f64::from(*r) * xn - f64::from(*rl) * xl;
                }
                y[w - 1] = diag[w - 1] * xr[w - 1]
                    - f64::from(right[w - 1]) * xr[0]
                    - f64::from(right[w - 2]) * xr[w - 2];
            }
            // Vertical neighbours; no edge across either pole.
            if i + 1 < h {
                let (dn_w, dn_x) = (&self.down[i * w..(i + 1) * w], &x[(i + 1) * w..(i + 2) * w]);
                for ((y, e), v) in y.iter_mut().zip(dn_w).zip(dn_x) {
                    *y -= f64::from(*e) * v;
                }
            }
            if i > 0 {
                let (up_w, up_x) = (&self.down[(i - 1) * w..i * w], &x[(i - 1) * w..i * w]);
                for ((y, e), v) in y.iter_mut().zip(up_w).zip(up_x) {
                    *y -= f64::from(*e) * v;
                }
            }
            dot += xr.iter().zip(y.iter()).map(|(x, y)| x * y).sum::<f64>();
        }
        dot
    }

    /// ‖A x − b‖ / ‖b‖ with a fixed-order reduction (row partial sums added in row order).
    /// A x exists only one row at a time: no grid-sized scratch.
    pub(crate) fn relative_residual(&self, x: &[f64]) -> f64 {
        let w = self.width;
        let (r, n) = ordered_sum2((0..self.height).into_par_iter().map_init(
            || vec![0.0f64; w],
            |ax, i| {
                self.apply_rows(x, ax, i);
                ax.iter()
                    .zip(&self.rhs[i * w..(i + 1) * w])
                    .fold((0.0, 0.0), |(r, n), (a, b)| {
                        (r + (a - b) * (a - b), n + b * b)
                    })
            },
        ));
        if n == 0.0 {
            r.sqrt()
        } else {
            (r / n).sqrt()
        }
    }
}
