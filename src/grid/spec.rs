//! The bin lattice: where bins are, how big, how they overlap.
//!
//! A [`Lattice`] is infinite and anchored at a fixed origin, so two runs over
//! different time slices (whose samples cover slightly different areas) bin
//! onto the *same* bins and can be merged. A [`GridSpec`] is a finite window
//! `[i0, i0+nx) × [j0, j0+ny)` of bin indices on a lattice; windows of
//! compatible runs are united on merge.

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// How a sample is weighted inside a bin.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Weighting {
    /// Every sample inside the `bin_w × bin_h` rectangle has weight 1.
    TopHat,
    /// Weight `exp(-½(dx²/σx² + dy²/σy²))` with `σ = bin/√12` (the second
    /// moment of the top-hat, so both have the same spatial resolution),
    /// truncated at 3σ (≈ 0.87 bin). Samples entering and leaving a bin
    /// change the estimate smoothly instead of by a step.
    Gaussian,
}

impl Weighting {
    /// Half-width of the support in units of the bin size.
    pub(crate) fn half_support(&self) -> f64 {
        match self {
            Weighting::TopHat => 0.5,
            Weighting::Gaussian => 3.0 * GAUSS_SIGMA,
        }
    }

    /// Weight at normalised offsets `(ξ, η)` from the bin centre (units of
    /// bin size), `None` outside the support.
    #[inline]
    pub(crate) fn weight(&self, xi: f64, eta: f64) -> Option<f64> {
        match self {
            Weighting::TopHat => {
                if (-0.5..0.5).contains(&xi) && (-0.5..0.5).contains(&eta) {
                    Some(1.0)
                } else {
                    None
                }
            }
            Weighting::Gaussian => {
                let h = 3.0 * GAUSS_SIGMA;
                if xi.abs() <= h && eta.abs() <= h {
                    let s2 = GAUSS_SIGMA * GAUSS_SIGMA;
                    Some((-0.5 * (xi * xi + eta * eta) / s2).exp())
                } else {
                    None
                }
            }
        }
    }
}

/// σ of the Gaussian weighting in bin units: 1/√12, the top-hat's rms width.
pub(crate) const GAUSS_SIGMA: f64 = 0.288_675_134_594_812_9;

/// An infinite regular lattice of (possibly overlapping, rectangular) bins.
///
/// Bin `i` along x spans `[origin_x + i·sx, origin_x + i·sx + bin_w)` with the
/// stride `sx = bin_w·(1 − overlap)`; its centre is at `origin_x + bin_w/2 +
/// i·sx`. The default origin −0.5 makes bins cover whole pixels (a pixel's
/// centre is at integer coordinates).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Lattice {
    /// Bin width along x (px).
    pub bin_w: f64,
    /// Bin height along y (px).
    pub bin_h: f64,
    /// Fraction of a bin shared with its neighbour, in [0, 1).
    pub overlap: f64,
    /// x of the lattice origin: the low-x edge of bin 0 (px).
    pub origin_x: f64,
    /// y of the lattice origin: the low-y edge of bin 0 (px).
    pub origin_y: f64,
}

impl Lattice {
    /// A lattice with square or rectangular bins; `overlap` in [0, 1).
    pub fn new(bin_w: f64, bin_h: f64, overlap: f64) -> Result<Lattice> {
        Lattice::with_origin(bin_w, bin_h, overlap, -0.5, -0.5)
    }

    /// A lattice with its origin at `(origin_x, origin_y)` (px); an error
    /// when a bin size is not positive and finite, `overlap` is outside
    /// [0, 1) or puts a sample into more than 64 bins per axis, or the
    /// origin is not finite.
    pub(crate) fn with_origin(
        bin_w: f64,
        bin_h: f64,
        overlap: f64,
        origin_x: f64,
        origin_y: f64,
    ) -> Result<Lattice> {
        for (name, b) in [("bin", bin_w), ("bin-h", bin_h)] {
            if !(b.is_finite() && b > 0.0) {
                return Err(Error::param(
                    name,
                    format!("bin size must be a positive number of pixels, got {b}"),
                ));
            }
        }
        if !(overlap.is_finite() && (0.0..1.0).contains(&overlap)) {
            return Err(Error::param(
                "overlap",
                format!("overlap must be in [0, 1) (fraction of the bin shared with the next bin), got {overlap}"),
            ));
        }
        // Overlap close to 1 would make every sample fall into thousands of bins.
        if 1.0 / (1.0 - overlap) > 64.0 {
            return Err(Error::param(
                "overlap",
                format!("overlap {overlap} puts each sample into more than 64 bins per axis"),
            ));
        }
        if !(origin_x.is_finite() && origin_y.is_finite()) {
            return Err(Error::param("origin", "lattice origin must be finite"));
        }
        Ok(Lattice {
            bin_w,
            bin_h,
            overlap,
            origin_x,
            origin_y,
        })
    }

    pub(crate) fn stride_x(&self) -> f64 {
        self.bin_w * (1.0 - self.overlap)
    }
    pub(crate) fn stride_y(&self) -> f64 {
        self.bin_h * (1.0 - self.overlap)
    }
    pub(crate) fn centre_x(&self, i: i64) -> f64 {
        self.origin_x + 0.5 * self.bin_w + i as f64 * self.stride_x()
    }
    pub(crate) fn centre_y(&self, j: i64) -> f64 {
        self.origin_y + 0.5 * self.bin_h + j as f64 * self.stride_y()
    }

    /// Inclusive range of bin indices along one axis whose support (half
    /// width `h` bin units around the centre) may contain `x`.
    fn range(x: f64, origin: f64, bin: f64, stride: f64, h: f64) -> (i64, i64) {
        let rel = x - origin - 0.5 * bin;
        let lo = ((rel - h * bin) / stride).floor() as i64;
        let hi = ((rel + h * bin) / stride).ceil() as i64;
        (lo, hi)
    }

    /// Candidate bin index ranges (inclusive) for a sample at (x, y); the
    /// exact membership test is [`Weighting::weight`].
    pub(crate) fn candidates(&self, x: f64, y: f64, w: Weighting) -> ((i64, i64), (i64, i64)) {
        let h = w.half_support();
        (
            Self::range(x, self.origin_x, self.bin_w, self.stride_x(), h),
            Self::range(y, self.origin_y, self.bin_h, self.stride_y(), h),
        )
    }

    /// Same bin geometry (to a relative 1e-12, so a JSON round trip is fine).
    pub(crate) fn compatible(&self, o: &Lattice) -> bool {
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * a.abs().max(b.abs()).max(1.0);
        close(self.bin_w, o.bin_w)
            && close(self.bin_h, o.bin_h)
            && close(self.overlap, o.overlap)
            && close(self.origin_x, o.origin_x)
            && close(self.origin_y, o.origin_y)
    }
}

/// A finite window of a lattice: bins `i0..i0+nx` × `j0..j0+ny`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GridSpec {
    /// The lattice the bins belong to.
    pub lattice: Lattice,
    /// Sample weighting inside a bin.
    pub weighting: Weighting,
    /// Lattice index along x of the window's first bin.
    pub i0: i64,
    /// Lattice index along y of the window's first bin.
    pub j0: i64,
    /// Number of bins along x.
    pub nx: usize,
    /// Number of bins along y.
    pub ny: usize,
}

/// Upper limit on the number of bins of one grid. Accumulation, estimation
/// and the outputs hold ~1.7 KB per bin (the accumulator's moment sums alone
/// are 768 B; measured peak: 6.4 GB for 3.7 M bins), so this caps a grid at
/// ~3.5 GB. A finer grid is refused, naming the bin size to change, before
/// anything is allocated.
pub(crate) const MAX_BINS: usize = 2_000_000;

/// The widest extent (px) of samples a grid accepts: four times the largest
/// sensor side. Positions further apart come from no sensor.
const MAX_EXTENT_PX: f64 = 4.0 * crate::io::guard::MAX_SENSOR_SIDE as f64;

impl GridSpec {
    /// The smallest window holding every bin that can receive a sample in
    /// the rectangle `[x_min, x_max] × [y_min, y_max]`.
    #[ebptv_macros::testkit]
    pub(crate) fn covering(
        lattice: Lattice,
        weighting: Weighting,
        x_min: f64,
        x_max: f64,
        y_min: f64,
        y_max: f64,
    ) -> Result<GridSpec> {
        if !(x_min.is_finite() && x_max.is_finite() && y_min.is_finite() && y_max.is_finite())
            || x_max < x_min
            || y_max < y_min
        {
            return Err(Error::param(
                "extent",
                format!("invalid extent x [{x_min}, {x_max}] y [{y_min}, {y_max}]"),
            ));
        }
        // The extent, not the bin size, is what is wrong when it is wider
        // than any sensor.
        if x_max - x_min > MAX_EXTENT_PX || y_max - y_min > MAX_EXTENT_PX {
            return Err(Error::param(
                "extent",
                format!(
                    "the samples span x [{x_min}, {x_max}], y [{y_min}, {y_max}] px, more than {MAX_EXTENT_PX} px: positions this far apart come from no sensor (damaged or foreign input?); check the input's x and y columns"
                ),
            ));
        }
        let ((i_lo, _), (j_lo, _)) = lattice.candidates(x_min, y_min, weighting);
        let ((_, i_hi), (_, j_hi)) = lattice.candidates(x_max, y_max, weighting);
        let (nx, ny) = ((i_hi - i_lo + 1) as f64, (j_hi - j_lo + 1) as f64);
        if nx * ny > MAX_BINS as f64 {
            return Err(Error::param(
                "bin",
                format!(
                    "the samples span x [{x_min}, {x_max}], y [{y_min}, {y_max}] px: {nx} x {ny} bins, more than {MAX_BINS} (~1.7 KB of memory each); use a larger bin or a smaller extent"
                ),
            ));
        }
        GridSpec::from_window(
            lattice,
            weighting,
            i_lo,
            j_lo,
            (i_hi - i_lo + 1) as usize,
            (j_hi - j_lo + 1) as usize,
        )
    }

    pub(crate) fn from_window(
        lattice: Lattice,
        weighting: Weighting,
        i0: i64,
        j0: i64,
        nx: usize,
        ny: usize,
    ) -> Result<GridSpec> {
        if nx == 0 || ny == 0 || nx.saturating_mul(ny) > MAX_BINS {
            return Err(Error::param(
                "bin",
                format!("grid of {nx} x {ny} bins is empty or larger than {MAX_BINS} bins (~1.7 KB of memory each); use a larger bin or a smaller extent"),
            ));
        }
        Ok(GridSpec {
            lattice,
            weighting,
            i0,
            j0,
            nx,
            ny,
        })
    }

    /// Number of bins of the window (`nx · ny`); flat index `j·nx + i`.
    #[ebptv_macros::testkit]
    pub(crate) fn n_bins(&self) -> usize {
        self.nx * self.ny
    }

    /// Bin centres along x (px), `nx` values.
    pub(crate) fn xs(&self) -> Vec<f64> {
        (0..self.nx)
            .map(|k| self.lattice.centre_x(self.i0 + k as i64))
            .collect()
    }
    /// Bin centres along y (px), `ny` values.
    pub(crate) fn ys(&self) -> Vec<f64> {
        (0..self.ny)
            .map(|k| self.lattice.centre_y(self.j0 + k as i64))
            .collect()
    }

    /// Row-major flat index of lattice bin (i, j), if inside the window.
    #[inline]
    pub(crate) fn flat(&self, i: i64, j: i64) -> Option<usize> {
        let a = i - self.i0;
        let b = j - self.j0;
        if a < 0 || b < 0 || a as usize >= self.nx || b as usize >= self.ny {
            None
        } else {
            Some(b as usize * self.nx + a as usize)
        }
    }

    /// Same lattice and weighting (windows may differ).
    pub(crate) fn compatible(&self, o: &GridSpec) -> bool {
        self.weighting == o.weighting && self.lattice.compatible(&o.lattice)
    }

    /// The smallest window holding both.
    pub(crate) fn union(&self, o: &GridSpec) -> Result<GridSpec> {
        let i0 = self.i0.min(o.i0);
        let j0 = self.j0.min(o.j0);
        let i1 = (self.i0 + self.nx as i64).max(o.i0 + o.nx as i64);
        let j1 = (self.j0 + self.ny as i64).max(o.j0 + o.ny as i64);
        GridSpec::from_window(
            self.lattice,
            self.weighting,
            i0,
            j0,
            (i1 - i0) as usize,
            (j1 - j0) as usize,
        )
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn candidates_contain_exactly_the_member_bins() {
        // Brute force: scan many bins and test membership directly.
        for &(w, ov) in &[
            (Weighting::TopHat, 0.0),
            (Weighting::TopHat, 0.5),
            (Weighting::TopHat, 0.75),
            (Weighting::Gaussian, 0.5),
        ] {
            let lat = Lattice::new(16.0, 4.0, ov).unwrap();
            for k in 0..500 {
                let x = -20.0 + k as f64 * 0.731;
                let y = -7.0 + k as f64 * 0.377;
                let ((ilo, ihi), (jlo, jhi)) = lat.candidates(x, y, w);
                for i in -40..80 {
                    for j in -40..200 {
                        let xi = (x - lat.centre_x(i)) / lat.bin_w;
                        let eta = (y - lat.centre_y(j)) / lat.bin_h;
                        if w.weight(xi, eta).is_some() {
                            assert!(
                                (ilo..=ihi).contains(&i) && (jlo..=jhi).contains(&j),
                                "{x} {y} bin {i},{j}"
                            );
                        }
                    }
                }
            }
        }
    }

    #[ebptv_macros::unit_test]
    fn top_hat_without_overlap_partitions_the_plane() {
        let lat = Lattice::new(8.0, 8.0, 0.0).unwrap();
        for k in 0..1000 {
            let x = k as f64 * 0.1 - 3.0;
            let ((ilo, ihi), (jlo, jhi)) = lat.candidates(x, x, Weighting::TopHat);
            let mut n = 0;
            for i in ilo..=ihi {
                for j in jlo..=jhi {
                    let xi = (x - lat.centre_x(i)) / 8.0;
                    let eta = (x - lat.centre_y(j)) / 8.0;
                    n += Weighting::TopHat.weight(xi, eta).is_some() as usize;
                }
            }
            assert_eq!(n, 1, "x = {x}");
        }
    }

    #[ebptv_macros::unit_test]
    fn bad_parameters_are_rejected() {
        assert!(Lattice::new(0.0, 8.0, 0.0).is_err());
        assert!(Lattice::new(-1.0, 8.0, 0.0).is_err());
        assert!(Lattice::new(8.0, f64::NAN, 0.0).is_err());
        assert!(Lattice::new(8.0, 8.0, 1.0).is_err());
        assert!(Lattice::new(8.0, 8.0, -0.1).is_err());
        let e = Lattice::new(8.0, 8.0, 1.5).unwrap_err().to_string();
        assert!(e.contains("overlap"), "{e}");
    }
}
