//! `grid::grid_to_dir`, the library call behind `ebptv grid`: the folder it
//! writes agrees with the in-memory chain, merged halves give the single
//! run, and inputs it cannot use are refused before any output exists.
use crate::grid_common::*;

use std::path::Path;

use ebptv::table::TableFormat;

use ebptv::grid::{
    self, grid_to_dir, EstimateOptions, Fit, GridDirOptions, GridInput, GridProgress, Sample,
};

fn options(input: GridInput) -> GridDirOptions {
    GridDirOptions {
        input,
        bin: grid::BinOptions {
            bin: 20.0,
            ..Default::default()
        },
        estimate: EstimateOptions {
            fit: Fit::Linear,
            min_count: 20,
            noise_rms: 0.0,
        },
        profile: None,
        fields_every: None,
        plots: false,
        calibration: None,
        mask: None,
        table_format: TableFormat::Csv,
    }
}

/// A column of a `grid.csv` (NaN for empty bins).
fn grid_col(path: &Path, name: &str) -> Vec<f64> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = header.iter().position(|h| *h == name).unwrap();
    lines
        .map(|l| l.split(',').nth(col).unwrap().parse::<f64>().unwrap())
        .collect()
}

fn grid_u(path: &Path) -> Vec<f64> {
    grid_col(path, "u")
}

/// A sheared flow with known Reynolds stresses and 3000 tracks of 10
/// samples through it, over 200 × 120 px.
fn shear_tracks() -> (Shear, Vec<Sample>) {
    let flow = Shear {
        u0: 300.0,
        shear: 2.0,
        su: 40.0,
        sv: 25.0,
        rho: -0.4,
    };
    let s = flow.tracks(200.0, 120.0, 3000, 10, 100.0, 0.8, 5);
    (flow, s)
}

#[test]
fn grid_to_dir_matches_the_chain_and_merges_to_the_single_run() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (flow, s) = shear_tracks();
    write_tracks(&d.join("all.csv"), &s);
    write_tracks(&d.join("a.csv"), &s[..12_345]);
    write_tracks(&d.join("b.csv"), &s[12_345..]);

    let mut binned = 0usize;
    let mut announced = 0usize;
    let run = grid_to_dir(
        &options(GridInput::Tracks(d.join("all.csv"))),
        &d.join("single"),
        &mut |p| match p {
            GridProgress::Binning { samples } => announced = samples,
            GridProgress::Binned(n) => binned += n,
            _ => {}
        },
    )
    .unwrap();
    assert_eq!((announced, binned), (s.len(), s.len()));
    assert_eq!(run.binned_samples, s.len() as u64);
    assert!(run.noise.as_ref().is_some_and(|n| n.is_ok()));

    // The in-memory chain on the same samples gives the same means.
    let acc =
        grid::accumulate(&s, &options(GridInput::Merge(vec![])).bin, "s", &mut |_| {}).unwrap();
    let g = grid::estimate(&acc, &options(GridInput::Merge(vec![])).estimate).unwrap();
    let single = grid_u(&d.join("single/grid.csv"));
    assert_eq!(single.len(), g.bins.len());
    assert_eq!(
        run.valid_bins,
        g.bins.iter().filter(|b| b.u.is_finite()).count()
    );
    assert!(run.valid_bins > 30, "{} valid bins", run.valid_bins);
    for (a, b) in single.iter().zip(&g.bins) {
        assert!(
            a.is_nan() == b.u.is_nan()
                && (a.is_nan() || (a - b.u).abs() < 1e-6 * b.u.abs().max(1.0))
        );
    }
    // And the mean flow is the flow's.
    let ys = grid_col(&d.join("single/grid.csv"), "y");
    let mid: Vec<f64> = single
        .iter()
        .zip(&ys)
        .filter(|(u, _)| u.is_finite())
        .map(|(u, y)| u - flow.mean_u(*y))
        .collect();
    assert!(median(mid.iter().map(|e| e.abs()).collect()) < 10.0);

    // Two halves binned apart and merged through their states.
    for h in ["a", "b"] {
        grid_to_dir(
            &options(GridInput::Tracks(d.join(format!("{h}.csv")))),
            &d.join(h),
            &mut |_| {},
        )
        .unwrap();
    }
    let merged = grid_to_dir(
        &options(GridInput::Merge(vec![
            d.join("a"),
            d.join("b/grid_state.json"),
        ])),
        &d.join("merged"),
        &mut |_| {},
    )
    .unwrap();
    assert_eq!(merged.binned_samples, run.binned_samples);
    assert!(merged.noise.is_none(), "states hold no samples");
    let m = grid_u(&d.join("merged/grid.csv"));
    assert_eq!(m.len(), single.len());
    for (a, b) in m.iter().zip(&single) {
        assert!(
            a.is_nan() == b.is_nan() && (a.is_nan() || (a - b).abs() < 1e-6 * b.abs().max(1.0))
        );
    }
}

#[test]
fn grid_to_dir_refuses_before_writing() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    write_tracks(
        &d.join("t.csv"),
        &[Sample {
            x: 1.0,
            y: 2.0,
            u: 3.0,
            v: 4.0,
            t_us: 0.0,
            track_id: 1,
        }],
    );
    let nothing = |_: GridProgress<'_>| {};
    // No state to merge.
    let e = grid_to_dir(&options(GridInput::Merge(vec![])), &d.join("o1"), &mut {
        nothing
    })
    .unwrap_err();
    assert!(e.to_string().contains("no grid state"), "{e}");
    // Time-resolved fields of merged states.
    let mut o = options(GridInput::Merge(vec![d.join("missing")]));
    o.fields_every = Some(2);
    let e = grid_to_dir(&o, &d.join("o2"), &mut { nothing }).unwrap_err();
    assert!(e.to_string().contains("fields_every"), "{e}");
    // A wall fit without a scale.
    let mut o = options(GridInput::Tracks(d.join("t.csv")));
    o.profile = Some(grid::ProfileOptions {
        x: 1.0,
        wall: Some(grid::WallSide::Top),
        wall_y: None,
        wall_points: 3,
        nu_m2_s: 1e-6,
        px_per_mm: None,
    });
    let e = grid_to_dir(&o, &d.join("o3"), &mut { nothing }).unwrap_err();
    assert!(e.to_string().contains("px_per_mm"), "{e}");
    for o in ["o1", "o2", "o3"] {
        assert!(!d.join(o).exists(), "{o} was created");
    }
}

/// Same-valued columns, NaN equal to NaN, bit for bit otherwise.
fn assert_same_table(a: &ebptv::compare::Table, b: &ebptv::compare::Table, what: &str) {
    assert_eq!(a.names, b.names, "{what}");
    for (n, (x, y)) in a.names.iter().zip(a.cols.iter().zip(&b.cols)) {
        assert_eq!(x.len(), y.len(), "{what} {n}");
        for (i, (p, q)) in x.iter().zip(y).enumerate() {
            assert!(
                p.to_bits() == q.to_bits() || (p.is_nan() && q.is_nan()),
                "{what} {n} row {i}: {p} vs {q}"
            );
        }
    }
}

/// The `grid` and `grid_extra` tables in Parquet and `.npy` hold the
/// columns and values of the CSV of the same run (the CSV writes every
/// value in shortest round-trip form, so equal means bit for bit), under
/// the format's own extension only.
#[test]
fn grid_tables_in_every_format_hold_the_csv_values() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Wider than the tracks: the edge bins stay empty.
    let (_, s) = shear_tracks();
    write_tracks(&d.join("all.csv"), &s);
    let run = |fmt: TableFormat| {
        let out = d.join(fmt.ext());
        let mut o = options(GridInput::Tracks(d.join("all.csv")));
        o.table_format = fmt;
        grid_to_dir(&o, &out, &mut |_| {}).unwrap();
        out
    };
    let csv = run(TableFormat::Csv);
    for fmt in [TableFormat::Parquet, TableFormat::Npy] {
        let out = run(fmt);
        for stem in ["grid", "grid_extra"] {
            let want = ebptv::compare::read_table(&csv.join(format!("{stem}.csv")), &[]).unwrap();
            let got = ebptv::compare::read_table(&out.join(fmt.file_name(stem)), &[]).unwrap();
            assert!(want.rows() > 50 && want.names.len() >= 8, "{stem}");
            assert_same_table(&want, &got, &format!("{fmt:?} {stem}"));
            assert!(!out.join(format!("{stem}.csv")).exists());
        }
        assert!(want_nan_bins(&out.join(fmt.file_name("grid"))));
    }
}

/// The table has empty bins (NaN means), so NaN goes through the format.
fn want_nan_bins(path: &Path) -> bool {
    let t = ebptv::compare::read_table(path, &["u"]).unwrap();
    t.col("u").unwrap().iter().any(|u| u.is_nan())
}
