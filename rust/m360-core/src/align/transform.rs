//! The per-pixel maps an alignment applies to the tangents, composed instead of applied one full
//! pass at a time.
//!
//! Aligning goes through pointwise affine steps: standardise each tangent, apply each solved
//! level's fields, undo the common standardisation. Applied as they come, each is a pass over the
//! whole tangent stack (four with the default schedule: about a third of the alignment's time at
//! 8K), although a level's problem reads the maps at a fixed budget of overlap samples only. A [`Transform`] keeps the steps instead: a problem reads the maps through it, computing
//! the few values it needs on demand ([`Transformed`]), and the stack is written once at the end
//! ([`Transform::apply`]).
//!
//! Each step is evaluated with the same f64 operations in the same order as a full pass would,
//! and rounded to f32 after each step as a stored map would be, so the result is the same, bit
//! for bit, as applying the steps one after the other (tested in `align.rs`).

use super::{grid_cell, LevelParams, Offsets};
use crate::layout::Layout;
use rayon::prelude::*;

/// The offset factor f(x, y) of every tangent pixel, separably: 1/√(1 + gx² + gy²) with the
/// gnomonic coordinates of column x and row y (perspective offsets), or 1 (spherical ones).
#[derive(Debug, Clone)]
pub(super) struct FactorTable {
    offsets: Offsets,
    width: usize,
    height: usize,
    gx2: Vec<f64>,
    gy2: Vec<f64>,
}

impl FactorTable {
    pub(super) fn new(layout: &Layout, offsets: Offsets) -> Self {
        let (h, w) = layout.tangent_shape();
        let mut gx2 = Vec::with_capacity(layout.cameras.len() * w);
        let mut gy2 = Vec::with_capacity(layout.cameras.len() * h);
        for cam in &layout.cameras {
            gx2.extend((0..w).map(|x| cam.gnomonic(x as f64, 0.0).0.powi(2)));
            gy2.extend((0..h).map(|y| cam.gnomonic(0.0, y as f64).1.powi(2)));
        }
        Self {
            offsets,
            width: w,
            height: h,
            gx2,
            gy2,
        }
    }

    /// Fill `out` (one tangent row) with the factors of row y of tangent t.
    pub(super) fn row(&self, t: usize, y: usize, out: &mut [f64]) {
        match self.offsets {
            Offsets::Spherical => out.fill(1.0),
            Offsets::Perspective => {
                let gy2 = self.gy2[t * self.height + y];
                let gx2 = &self.gx2[t * self.width..(t + 1) * self.width];
                for (f, &g) in out.iter_mut().zip(gx2) {
                    *f = 1.0 / (1.0 + g + gy2).sqrt();
                }
            }
        }
    }

    /// The factor of pixel (x, y) of tangent t: the same number [`FactorTable::row`] gives.
    fn at(&self, t: usize, y: usize, x: usize) -> f64 {
        match self.offsets {
            Offsets::Spherical => 1.0,
            Offsets::Perspective => {
                let gy2 = self.gy2[t * self.height + y];
                1.0 / (1.0 + self.gx2[t * self.width + x] + gy2).sqrt()
            }
        }
    }
}

/// One level's solved fields with their interpolation tables: bilinear s and o over a
/// `cols`×`rows` grid of nodes spanning each tangent.
#[derive(Debug, Clone)]
struct Fields {
    cols: usize,
    rows: usize,
    /// Node-interleaved (s, o), as the solver returns them.
    x: Vec<f64>,
    /// Per tangent column: the grid column left of it and the fraction towards the next.
    columns: Vec<(usize, f64)>,
    /// The tangent columns between each grid column and the next, left to right: (grid
    /// column, first tangent column, end).
    spans: Vec<(usize, usize, usize)>,
    /// Per tangent row: the grid row above it and the fraction towards the next.
    lines: Vec<(usize, f64)>,
}

impl Fields {
    fn new(h: usize, w: usize, params: &LevelParams, x: Vec<f64>) -> Self {
        let (cols, rows) = (params.cols, params.rows);
        let columns: Vec<(usize, f64)> = (0..w)
            .map(|xp| {
                let (c0, _, fx, _) = grid_cell(xp as f64, 0.0, w, h, cols, rows);
                (c0, fx)
            })
            .collect();
        let mut spans: Vec<(usize, usize, usize)> = Vec::new();
        for (x, &(c0, _)) in columns.iter().enumerate() {
            match spans.last_mut() {
                Some(span) if span.0 == c0 => span.2 = x + 1,
                _ => spans.push((c0, x, x + 1)),
            }
        }
        let lines = (0..h)
            .map(|y| {
                let (_, r0, _, fy) = grid_cell(0.0, y as f64, w, h, cols, rows);
                (r0, fy)
            })
            .collect();
        Self {
            cols,
            rows,
            x,
            columns,
            spans,
            lines,
        }
    }

    /// The fields of tangent t interpolated down to row y at the grid columns: (s, o) per grid
    /// column, interleaved, into `out` (2·cols).
    fn line(&self, t: usize, y: usize, out: &mut [f64]) {
        let (r0, fy) = self.lines[y];
        let start = 2 * (t * self.cols * self.rows + r0 * self.cols);
        let top = &self.x[start..start + 2 * self.cols];
        let bottom = &self.x[start + 2 * self.cols..start + 4 * self.cols];
        for ((v, a), b) in out.iter_mut().zip(top).zip(bottom) {
            *v = (1.0 - fy) * a + fy * b;
        }
    }

    /// `row` (offset factors `f`) ← s·v + o·f, for a row whose [`Fields::line`] is `line`: one
    /// grid cell's span of columns at a time, so the inner loop has no table look-up and
    /// vectorises.
    fn apply_row(&self, line: &[f64], f: &[f64], row: &mut [f32]) {
        for &(c0, start, end) in &self.spans {
            let pair = &line[2 * c0..2 * c0 + 4];
            let (columns, f) = (&self.columns[start..end], &f[start..end]);
            for ((v, &(_, fx)), &f) in row[start..end].iter_mut().zip(columns).zip(f) {
                *v = affine(pair, fx, *v, f);
            }
        }
    }

    /// s·v + o·f at pixel (x, y) of tangent t: [`Fields::line`] at the two grid columns around
    /// x only (the same numbers), then the same interpolation as [`Fields::apply_row`].
    fn apply_pixel(&self, t: usize, y: usize, x: usize, f: f64, v: f32) -> f32 {
        let (c0, fx) = self.columns[x];
        let (r0, fy) = self.lines[y];
        let start = 2 * (t * self.cols * self.rows + r0 * self.cols + c0);
        let below = start + 2 * self.cols;
        let mut pair = [0.0; 4];
        for (k, p) in pair.iter_mut().enumerate() {
            *p = (1.0 - fy) * self.x[start + k] + fy * self.x[below + k];
        }
        affine(&pair, fx, v, f)
    }
}

/// s·v + o·f with s and o interpolated at fraction `fx` between two grid columns' (s, o):
/// `pair` = [s0, o0, s1, o1].
#[inline]
fn affine(pair: &[f64], fx: f64, v: f32, f: f64) -> f32 {
    let s = (1.0 - fx) * pair[0] + fx * pair[2];
    let o = (1.0 - fx) * pair[1] + fx * pair[3];
    (s * f64::from(v) + o * f) as f32
}

/// One pointwise step.
#[derive(Debug, Clone)]
enum Step {
    /// Per tangent (median m, spread): v ← (v − m·f)/spread (1/spread = 1 where the spread is 0).
    Standardize(Vec<(f64, f64)>),
    /// v ← s(x)·v + o(x)·f(x).
    Fields(Fields),
    /// v ← v·spread + median, the same for every tangent.
    Restore { spread: f64, median: f64 },
}

impl Step {
    /// `row` (row y of tangent t, with the offset factors `f`) through the step; `line` is
    /// scratch of at least 2·cols.
    fn apply_row(&self, t: usize, y: usize, f: &[f64], row: &mut [f32], line: &mut Vec<f64>) {
        match self {
            Self::Standardize(stats) => {
                let (m, inv) = standardizing(stats[t]);
                for (v, &f) in row.iter_mut().zip(f) {
                    *v = ((f64::from(*v) - m * f) * inv) as f32;
                }
            }
            Self::Fields(fields) => {
                line.resize(2 * fields.cols, 0.0);
                fields.line(t, y, line);
                fields.apply_row(line, f, row);
            }
            Self::Restore { spread, median } => {
                for v in row.iter_mut() {
                    *v = (f64::from(*v) * spread + median) as f32;
                }
            }
        }
    }

    /// Value `v` of pixel (x, y) of tangent t, with offset factor `f`, through the step.
    fn apply_pixel(&self, t: usize, y: usize, x: usize, f: f64, v: f32) -> f32 {
        match self {
            Self::Standardize(stats) => {
                let (m, inv) = standardizing(stats[t]);
                ((f64::from(v) - m * f) * inv) as f32
            }
            Self::Fields(fields) => fields.apply_pixel(t, y, x, f, v),
            Self::Restore { spread, median } => (f64::from(v) * spread + median) as f32,
        }
    }
}

/// (median, 1/spread) of a tangent's standardisation (1/spread = 1 for a constant tangent).
fn standardizing((median, spread): (f64, f64)) -> (f64, f64) {
    (median, if spread > 0.0 { 1.0 / spread } else { 1.0 })
}

/// Pointwise steps to apply to tangent maps, in order (see the module documentation).
#[derive(Debug, Clone)]
pub(super) struct Transform {
    factors: FactorTable,
    height: usize,
    width: usize,
    steps: Vec<Step>,
}

impl Transform {
    /// No step yet, with the offset factors of `offsets`.
    pub(super) fn new(layout: &Layout, offsets: Offsets) -> Self {
        let (height, width) = layout.tangent_shape();
        Self {
            factors: FactorTable::new(layout, offsets),
            height,
            width,
            steps: Vec::new(),
        }
    }

    /// The offset factors.
    pub(super) fn factors(&self) -> &FactorTable {
        &self.factors
    }

    /// Then standardise tangent t with (median, spread) `stats[t]`.
    pub(super) fn standardize(&mut self, stats: Vec<(f64, f64)>) {
        self.steps.push(Step::Standardize(stats));
    }

    /// Then apply fields `x` (node-interleaved s, o) on the grid of `params`.
    pub(super) fn fields(&mut self, params: &LevelParams, x: Vec<f64>) {
        self.steps.push(Step::Fields(Fields::new(
            self.height,
            self.width,
            params,
            x,
        )));
    }

    /// Then v ← v·spread + median.
    pub(super) fn restore(&mut self, spread: f64, median: f64) {
        self.steps.push(Step::Restore { spread, median });
    }

    /// Apply every step to `maps` (N·h·w) in place, one row at a time.
    pub(super) fn apply(&self, maps: &mut [f32]) {
        let w = self.width;
        maps.par_chunks_mut(w).enumerate().for_each_init(
            || (vec![0.0; w], Vec::new()),
            |(f_row, line), (face_row, row)| self.apply_row(face_row, row, f_row, line),
        );
    }

    /// [`Transform::apply`] from `maps` into `out` (the same size), leaving `maps` as it is.
    pub(super) fn apply_into(&self, maps: &[f32], out: &mut [f32]) {
        let w = self.width;
        out.par_chunks_mut(w)
            .zip(maps.par_chunks(w))
            .enumerate()
            .for_each_init(
                || (vec![0.0; w], Vec::new()),
                |(f_row, line), (face_row, (row, raw))| {
                    row.copy_from_slice(raw);
                    self.apply_row(face_row, row, f_row, line);
                },
            );
    }

    /// Every step on `row`, row `face_row` of the stack (`f_row` and `line`: scratch).
    fn apply_row(&self, face_row: usize, row: &mut [f32], f_row: &mut [f64], line: &mut Vec<f64>) {
        let (t, y) = (face_row / self.height, face_row % self.height);
        self.factors.row(t, y, f_row);
        for step in &self.steps {
            step.apply_row(t, y, f_row, row, line);
        }
    }

    /// The value at flat index `index` (tangent·h·w + y·w + x) of `maps` after every step.
    fn value(&self, maps: &[f32], index: usize) -> f32 {
        self.value_of(index, maps[index])
    }

    /// Raw value `raw` at flat index `index` after every step (the steps are per pixel).
    fn value_of(&self, index: usize, raw: f32) -> f32 {
        let (h, w) = (self.height, self.width);
        let (t, p) = (index / (h * w), index % (h * w));
        let (y, x) = (p / w, p % w);
        let f = self.factors.at(t, y, x);
        self.steps
            .iter()
            .fold(raw, |v, step| step.apply_pixel(t, y, x, f, v))
    }
}

/// Tangent maps read by flat index: a slice, or maps through a `Transform` (computed on
/// demand).
pub trait MapValues: Sync {
    /// The value at flat index `index` (tangent·h·w + y·w + x).
    fn value(&self, index: usize) -> f32;

    /// A raw value `raw` standing at flat index `index`, read the same way (the identity for
    /// plain maps; through the steps of a transform).
    fn through(&self, index: usize, raw: f32) -> f32 {
        let _ = index;
        raw
    }
}

impl MapValues for [f32] {
    #[inline]
    fn value(&self, index: usize) -> f32 {
        self[index]
    }
}

/// `maps` as they would be after `transform`, without applying it.
pub(super) struct Transformed<'a> {
    pub(super) maps: &'a [f32],
    pub(super) transform: &'a Transform,
}

impl MapValues for Transformed<'_> {
    fn value(&self, index: usize) -> f32 {
        self.transform.value(self.maps, index)
    }

    fn through(&self, index: usize, raw: f32) -> f32 {
        self.transform.value_of(index, raw)
    }
}
