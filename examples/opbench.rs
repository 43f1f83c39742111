use refnpr::tensor_util::*;
use std::time::Instant;
use burn::tensor::{Tensor, IndexingUpdateOp};
fn main() {
    let b: refnpr::BackendKind = std::env::args().nth(1).unwrap_or("flex".into()).parse().unwrap();
    let dev = b.device();
    let rows = 500_000usize; let c = 28; let s = 1_000_000usize;
    let table = floats(vec![0.5; rows*c], [rows, c], &dev);
    let idx: Vec<i32> = (0..s).map(|i| ((i as u64 * 2654435761) % rows as u64) as i32).collect();
    let it = indices(idx.clone(), &dev);
    let w = floats(vec![0.3; s], [s, 1], &dev);
    for _ in 0..3 {
        let t = Instant::now();
        let g = table.clone().select(0, it.clone());
        let _ = to_vec(g.clone().sum());
        let t1 = t.elapsed();
        let t = Instant::now();
        let gw = g * w.clone();
        let _ = to_vec(gw.clone().sum());
        let t2 = t.elapsed();
        let t = Instant::now();
        let r = gw.reshape([s/8, 8, c]).sum_dim(1);
        let _ = to_vec(r.sum());
        let t3 = t.elapsed();
        let t = Instant::now();
        let z: Tensor<2> = Tensor::zeros([rows, c], &dev);
        let z = z.select_assign(0, it.clone(), floats(vec![0.1; s*c], [s, c], &dev), IndexingUpdateOp::Add);
        let _ = to_vec(z.sum());
        let t4 = t.elapsed();
        let t = Instant::now();
        let big: Tensor<2> = Tensor::zeros([2_000_000, c], &dev);
        let upd = floats(vec![0.1; rows*c], [rows, c], &dev);
        let ridx = indices((0..rows as i32).map(|i| i*4).collect(), &dev);
        let big = big.select_assign(0, ridx, upd, IndexingUpdateOp::Add);
        let _ = to_vec(big.narrow(0,0,1).sum());
        let t5 = t.elapsed();
        println!("select {t1:?} mul {t2:?} reshape-sum {t3:?} select_assign-add {t4:?} big-assign {t5:?}");
    }
}
