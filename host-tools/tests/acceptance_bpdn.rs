//! Sparse estimation (issue 3, sparse paper section 4.2): BPDN-SV and BPDN-AIC on B2
//! (Example I, N = 75, 25 dB) over a range of past windows. The target (a mean
//! VAF of at least 95 at every p in 3..14) is not reached yet: this test pins what the implementation
//! does today (about 90-92 for p = 3..10) so a regression shows, and prints the table.

use lpvid_host::metrics::{mean, vaf_per_output};
use lpvid_host::pbsid::{fit, PbsidOptions, Reg};
use lpvid_host::systems;

fn mean_vaf(p: usize, reg: Reg, runs: u64) -> f64 {
    let mut v = Vec::new();
    for seed in 0..runs {
        let e = systems::b2(75, 25.0, seed);
        let mut o = PbsidOptions::new(p);
        o.reg = reg;
        let f = fit(&e.train, &o).expect("fit");
        v.push(mean(&vaf_per_output(
            &e.val.y,
            &f.model.simulate(&e.val, None),
            0,
        )));
    }
    mean(&v)
}

#[test]
fn b2_bpdn_over_past_windows() {
    println!("B2, N = 75, 25 dB, 10 runs: mean VAF");
    println!("   p   BPDN-SV   BPDN-AIC   Tikhonov-GCV");
    for p in [3usize, 5, 8, 10] {
        let sv = mean_vaf(p, Reg::BpdnSv, 10);
        let aic = mean_vaf(p, Reg::BpdnAic, 10);
        let tik = mean_vaf(p, Reg::TikhonovGcv, 10);
        println!("  {p:2}   {sv:7.2}   {aic:8.2}   {tik:12.2}");
        assert!(sv >= 85.0, "BPDN-SV at p = {p}: {sv}");
    }
}
