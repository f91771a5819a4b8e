//! The scheduling centre chosen by the free run (`pipeline::identify`, `--centre auto`) on
//! plant families whose p1 has 0 away from its mean: every scheduled family plant of two seed
//! ranges with p1 moved by 0.5 and by 1 (its standard deviation is 0.5-0.7, so 0 lies 0.7-2
//! standard deviations from the mean, inside the range or at its edge), against the fits at
//! 0 and at the mean alone. Release mode: 3 x 2 x 83 fits.

#[path = "centre_support/mod.rs"]
mod centre;

#[test]
fn the_centre_chosen_by_the_free_run_beats_both_fixed_centres_on_plant_families() {
    let mut cases = centre::scheduled_cases(4, 1500, 1000);
    cases.extend(centre::scheduled_cases(4, 1500, 61000));
    assert_eq!(cases.len(), 83);
    let threads = std::thread::available_parallelism().map_or(1, |v| v.get());
    for offset in [0.5, 1.0] {
        let rows = centre::errors(&cases, offset, threads);
        let (zero, mean, auto) = (
            centre::mean_log10(&rows, 0),
            centre::mean_log10(&rows, 1),
            centre::mean_log10(&rows, 2),
        );
        // how often auto lost more than 10 % against the better of the two fixed centres
        let lost = rows.iter().filter(|e| e[2] > 1.1 * e[0].min(e[1])).count();
        println!("offset {offset}: mean log10 error zero {zero:.3}, mean {mean:.3}, auto {auto:.3}; auto more than 10 % worse than the better fixed centre on {lost} of {}", rows.len());
        // measured (ranges 1000 and 61000): offset 0.5 zero -1.062, mean -1.122, auto -1.139,
        // lost on 2 of 83; offset 1 zero -0.922, mean -1.122, auto -1.136, lost on 0
        assert!(auto < zero - 0.05, "auto {auto} against zero {zero}");
        assert!(auto < mean + 0.02, "auto {auto} against mean {mean}");
        assert!(lost * 10 <= rows.len(), "{lost} of {}", rows.len());
    }
}
