//! The sparsity pattern of a level's Hessian, and where each term's entries go in it.
//!
//! The pattern depends on the grid and on which cells the samples fall in, not on their values
//! or weights. A batch or a video stitches the same layout image after image with the same
//! deterministic sample pixels, so patterns are kept across problems: building one (about a
//! million node pairs on a prior-only level) and finding every term's entries in it cost about
//! as much as that level's Newton step (docs/method.md, "Global prior", Cost).

use rayon::prelude::*;
use std::sync::{Arc, Mutex, PoisonError};

/// What a pattern is made of: node lists of the terms that couple nodes.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(super) struct Couplings {
    /// Unknown nodes in all (2 unknowns each).
    pub(super) nodes: usize,
    /// The 8 nodes of each group of data samples, in group order.
    pub(super) data: Vec<[u32; 8]>,
    /// The 5 nodes of each group of prior samples (the cell's 4, then the prior's), in order.
    pub(super) prior: Vec<[u32; 5]>,
    /// The smoothness edges (p, q).
    pub(super) edges: Vec<[u32; 2]>,
}

/// The 2×2-block compressed-row pattern of a Hessian, with each term's block positions.
#[derive(Debug, Default)]
pub(super) struct Pattern {
    couplings: Couplings,
    /// Row node p couples with `col[start[p]..start[p + 1]]` (ascending).
    pub(super) start: Vec<usize>,
    pub(super) col: Vec<u32>,
    /// Position in `col` of node pair (u, v) of data group g: `data_at[64·g + 8·u + v]`.
    pub(super) data_at: Vec<u32>,
    /// Of prior group g: `prior_at[25·g + 5·u + v]`.
    pub(super) prior_at: Vec<u32>,
    /// Of edge (p, q): positions of (p, p), (q, q), (p, q), (q, p).
    pub(super) edge_at: Vec<[u32; 4]>,
    /// Of (p, p).
    pub(super) diagonal_at: Vec<u32>,
}

/// How many patterns are kept (most recently used): a stitch with a prior uses about three,
/// one without it two.
const PATTERNS_KEPT: usize = 8;
/// Patterns with more entries than this are not kept.
const PATTERN_MAX_ENTRIES: usize = 1 << 22;

static PATTERNS: Mutex<Vec<Arc<Pattern>>> = Mutex::new(Vec::new());

impl Pattern {
    /// The pattern of `couplings`, kept or made. A kept one is the one a fresh build gives.
    pub(super) fn of(couplings: Couplings) -> Arc<Self> {
        Self::kept_in(&PATTERNS, couplings)
    }

    /// [`Pattern::of`] with the patterns kept in `patterns`.
    fn kept_in(patterns: &Mutex<Vec<Arc<Self>>>, couplings: Couplings) -> Arc<Self> {
        {
            let mut kept = patterns.lock().unwrap_or_else(PoisonError::into_inner);
            if let Some(at) = kept.iter().position(|p| p.couplings == couplings) {
                let hit = kept.remove(at);
                kept.push(Arc::clone(&hit));
                return hit;
            }
        }
        // Made outside the lock: other threads' assemblies need not wait for this one.
        let made = Arc::new(Self::build(couplings));
        if made.col.len() <= PATTERN_MAX_ENTRIES {
            let mut kept = patterns.lock().unwrap_or_else(PoisonError::into_inner);
            if !kept.iter().any(|p| p.couplings == made.couplings) {
                kept.push(Arc::clone(&made));
                if kept.len() > PATTERNS_KEPT {
                    kept.remove(0);
                }
            }
        }
        made
    }

    fn build(couplings: Couplings) -> Self {
        let n = couplings.nodes;
        let visit = |f: &mut dyn FnMut(u32, u32)| {
            for nd in &couplings.data {
                for &p in nd {
                    for &q in nd {
                        f(p, q);
                    }
                }
            }
            for nd in &couplings.prior {
                for &p in nd {
                    for &q in nd {
                        f(p, q);
                    }
                }
            }
            for &[p, q] in &couplings.edges {
                f(p, q);
                f(q, p);
            }
            for i in 0..n as u32 {
                f(i, i);
            }
        };
        // Bucketed by row, then each row sorted and deduplicated: the pattern of one sort of
        // all pairs, without that sort.
        let mut row_start = vec![0usize; n + 1];
        visit(&mut |p, _| row_start[p as usize + 1] += 1);
        for p in 0..n {
            row_start[p + 1] += row_start[p];
        }
        let mut columns = vec![0u32; row_start[n]];
        let mut fill = row_start.clone();
        visit(&mut |p, q| {
            columns[fill[p as usize]] = q;
            fill[p as usize] += 1;
        });
        let mut rows = Vec::with_capacity(n);
        let mut rest = columns.as_mut_slice();
        for p in 0..n {
            let (row, tail) = rest.split_at_mut(row_start[p + 1] - row_start[p]);
            rows.push(row);
            rest = tail;
        }
        rows.par_iter_mut().for_each(|row| row.sort_unstable());
        let mut start = Vec::with_capacity(n + 1);
        let mut col = Vec::with_capacity(columns.len());
        start.push(0);
        for p in 0..n {
            let first = col.len();
            for &q in &columns[row_start[p]..row_start[p + 1]] {
                if col.len() == first || col.last() != Some(&q) {
                    col.push(q);
                }
            }
            start.push(col.len());
        }
        let at = |p: u32, q: u32| -> u32 {
            let (lo, hi) = (start[p as usize], start[p as usize + 1]);
            let found = col[lo..hi]
                .binary_search(&q)
                .unwrap_or_else(|_| unreachable!("block ({p}, {q}) is in the pattern"));
            (lo + found) as u32
        };
        let data_at = all_pairs(&couplings.data, &at);
        let prior_at = all_pairs(&couplings.prior, &at);
        let edge_at = couplings
            .edges
            .par_iter()
            .map(|&[p, q]| [at(p, p), at(q, q), at(p, q), at(q, p)])
            .collect();
        let diagonal_at = (0..n as u32).into_par_iter().map(|p| at(p, p)).collect();
        Self {
            couplings,
            start,
            col,
            data_at,
            prior_at,
            edge_at,
            diagonal_at,
        }
    }

    /// Whether no pattern was built yet (a problem before its first assembly).
    pub(super) fn is_empty(&self) -> bool {
        self.start.is_empty()
    }
}

/// `at(p, q)` of every node pair (p, q) of each group, row-major per group, groups in order.
fn all_pairs<const N: usize>(
    groups: &[[u32; N]],
    at: &(impl Fn(u32, u32) -> u32 + Sync),
) -> Vec<u32> {
    groups
        .par_iter()
        .flat_map_iter(|nd| {
            nd.iter()
                .flat_map(move |&p| nd.iter().map(move |&q| at(p, q)))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A dense boolean oracle of which node pairs couple.
    fn dense(c: &Couplings) -> Vec<Vec<bool>> {
        let mut m = vec![vec![false; c.nodes]; c.nodes];
        let mut mark = |nd: &[u32]| {
            for &p in nd {
                for &q in nd {
                    m[p as usize][q as usize] = true;
                }
            }
        };
        c.data.iter().for_each(|nd| mark(nd));
        c.prior.iter().for_each(|nd| mark(nd));
        c.edges.iter().for_each(|e| mark(e));
        (0..c.nodes as u32).for_each(|p| mark(&[p]));
        m
    }

    fn couplings(seed: u32) -> Couplings {
        let nodes = 40;
        let mix = seed.wrapping_mul(0x9E37_79B9);
        let pick = |k: u32| (k.wrapping_mul(2_654_435_761).wrapping_add(mix) >> 7) % 39;
        Couplings {
            nodes,
            data: (0..6)
                .map(|g| std::array::from_fn(|j| pick(8 * g + j as u32)))
                .collect(),
            prior: (0..5)
                .map(|g| {
                    let mut nd: [u32; 5] = std::array::from_fn(|j| pick(100 + 5 * g + j as u32));
                    nd[4] = 39; // the prior node
                    nd
                })
                .collect(),
            edges: (0..38).map(|p| [p, p + 1]).collect(),
        }
    }

    #[test]
    fn pattern_and_positions_match_a_dense_oracle() {
        for seed in 0..4 {
            let c = couplings(seed);
            let oracle = dense(&c);
            let p = Pattern::build(c.clone());
            for (row, marks) in oracle.iter().enumerate() {
                let want: Vec<u32> = (0..c.nodes as u32).filter(|&q| marks[q as usize]).collect();
                assert_eq!(p.col[p.start[row]..p.start[row + 1]], want[..], "row {row}");
            }
            let row_of = |pos: u32| p.start.partition_point(|&s| s <= pos as usize) - 1;
            let check = |pos: u32, a: u32, b: u32| {
                assert_eq!((row_of(pos), p.col[pos as usize]), (a as usize, b));
            };
            for (g, nd) in c.data.iter().enumerate() {
                for (u, &a) in nd.iter().enumerate() {
                    for (v, &b) in nd.iter().enumerate() {
                        check(p.data_at[64 * g + 8 * u + v], a, b);
                    }
                }
            }
            for (g, nd) in c.prior.iter().enumerate() {
                for (u, &a) in nd.iter().enumerate() {
                    for (v, &b) in nd.iter().enumerate() {
                        check(p.prior_at[25 * g + 5 * u + v], a, b);
                    }
                }
            }
            for (e, &[a, b]) in c.edges.iter().enumerate() {
                let at = p.edge_at[e];
                check(at[0], a, a);
                check(at[1], b, b);
                check(at[2], a, b);
                check(at[3], b, a);
            }
            for q in 0..c.nodes as u32 {
                check(p.diagonal_at[q as usize], q, q);
            }
        }
    }

    #[test]
    fn a_kept_pattern_is_returned_for_the_same_couplings_only() {
        // A cache of its own: the other tests' problems use the shared one meanwhile.
        let patterns = Mutex::new(Vec::new());
        let a = Pattern::kept_in(&patterns, couplings(11));
        let b = Pattern::kept_in(&patterns, couplings(11));
        assert!(Arc::ptr_eq(&a, &b));
        let mut other = couplings(11);
        other.edges.pop();
        let c = Pattern::kept_in(&patterns, other);
        assert!(!Arc::ptr_eq(&a, &c));
        assert_eq!(c.edge_at.len() + 1, a.edge_at.len());
        for k in 0..PATTERNS_KEPT {
            Pattern::kept_in(&patterns, couplings(100 + k as u32));
        }
        let d = Pattern::kept_in(&patterns, couplings(11));
        assert!(!Arc::ptr_eq(&a, &d), "the oldest pattern is dropped first");
        assert_eq!(
            (a.start.clone(), a.col.clone()),
            (d.start.clone(), d.col.clone())
        );
    }
}
