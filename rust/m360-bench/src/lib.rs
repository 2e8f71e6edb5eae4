//! Criterion benchmarks of `m360-core`'s hot paths: `benches/core.rs`, run with
//! `cargo bench -p m360-bench`. The library itself is empty.
