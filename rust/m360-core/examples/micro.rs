use m360_core::Layout;
use m360_core::resample::ErpTaps;
use std::time::Instant;
fn main() {
    let layout = Layout::icosahedron(2048, 0.3, None).unwrap();
    for _ in 0..5 { let t = Instant::now(); let e = ErpTaps::build(&layout); println!("{:?} {}", t.elapsed(), e.len()); }
}
