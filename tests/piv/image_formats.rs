//! `ebptv piv-images` on every image kind PIV cameras and peers write:
//! BMP (grey and colour), palette TIFF, 16-bit multi-page TIFF stacks and
//! a pattern of PNG frames in natural order. Each test writes its own
//! files of synthetic particles moving by a known shift.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use ebptv::piv::images::save_png16;
use ebptv::piv::synth::{particle_frames, SynthOptions};
use ebptv::piv::Image;

const SHIFT: (f64, f64) = (2.4, -1.2);

fn frames(n: usize) -> Vec<Image> {
    let so = SynthOptions {
        width: 96,
        height: 80,
        frames: n,
        seed: 5,
        ..Default::default()
    };
    particle_frames(&so, &|_, _| SHIFT)
}

/// Samples of `im` scaled to `0..=max` (the brightest pixel at `max`).
fn scaled(im: &Image, max: f32) -> Vec<f32> {
    let top = im.data.iter().cloned().fold(f32::MIN, f32::max).max(1e-9);
    im.data.iter().map(|v| (v / top * max).round()).collect()
}

/// `ebptv --table-format csv piv-images ARGS… --window 32 --spacing 16
/// --out OUT`.
fn run(args: &[&str], out: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .args(["--table-format", "csv", "piv-images"])
        .args(args)
        .args(["--window", "32", "--spacing", "16", "--out"])
        .arg(out)
        .output()
        .unwrap()
}

/// The run succeeded, wrote `fields` vector files, and in each the valid
/// vectors (at least 80 %) show the known shift.
fn assert_shift(r: &Output, out: &Path, fields: usize) {
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    for s in 0..fields {
        let p = out.join(format!("vectors_{s:05}.csv"));
        let csv = std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
        let (mut good, mut all) = (0, 0);
        for l in csv.lines().skip(1) {
            let f: Vec<f64> = l.split(',').map(|s| s.parse().unwrap()).collect();
            all += 1;
            if f[4] == 0.0 {
                assert!(
                    (f[2] - SHIFT.0).abs() < 0.15 && (f[3] - SHIFT.1).abs() < 0.15,
                    "{}: {l}",
                    p.display()
                );
                good += 1;
            }
        }
        assert!(all > 0 && good * 5 >= all * 4, "{good} of {all} valid");
    }
    assert!(!out.join(format!("vectors_{fields:05}.csv")).exists());
}

fn path_str(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Pixels of [`write_bmp`], rows top to bottom.
enum Bmp<'a> {
    /// 8-bit indices into a grey palette (index = grey level).
    Grey8(&'a [u8]),
    /// R, G, B bytes per pixel.
    Rgb24(&'a [u8]),
}

/// A minimal uncompressed Windows BMP (BITMAPINFOHEADER, bottom-up rows
/// padded to 4 bytes), written from the format's definition.
fn write_bmp(path: &Path, w: u32, h: u32, px: Bmp) {
    let (bpp, palette, bytes_pp) = match px {
        Bmp::Grey8(_) => (8u16, 256u32, 1usize),
        Bmp::Rgb24(_) => (24, 0, 3),
    };
    let row = (w as usize * bytes_pp).div_ceil(4) * 4;
    let data_off = 14 + 40 + 4 * palette;
    let size = data_off + (row * h as usize) as u32;
    let mut b: Vec<u8> = Vec::new();
    b.extend_from_slice(b"BM");
    b.extend_from_slice(&size.to_le_bytes());
    b.extend_from_slice(&[0; 4]);
    b.extend_from_slice(&data_off.to_le_bytes());
    b.extend_from_slice(&40u32.to_le_bytes());
    b.extend_from_slice(&(w as i32).to_le_bytes());
    b.extend_from_slice(&(h as i32).to_le_bytes());
    b.extend_from_slice(&1u16.to_le_bytes());
    b.extend_from_slice(&bpp.to_le_bytes());
    b.extend_from_slice(&0u32.to_le_bytes()); // BI_RGB
    b.extend_from_slice(&((row * h as usize) as u32).to_le_bytes());
    b.extend_from_slice(&2835i32.to_le_bytes());
    b.extend_from_slice(&2835i32.to_le_bytes());
    b.extend_from_slice(&palette.to_le_bytes());
    b.extend_from_slice(&0u32.to_le_bytes());
    for k in 0..palette {
        b.extend_from_slice(&[k as u8, k as u8, k as u8, 0]);
    }
    for y in (0..h as usize).rev() {
        let start = b.len();
        let line = y * w as usize * bytes_pp..(y + 1) * w as usize * bytes_pp;
        match px {
            Bmp::Grey8(v) => b.extend_from_slice(&v[line]),
            // BMP stores blue, green, red.
            Bmp::Rgb24(v) => {
                for p in v[line].chunks_exact(3) {
                    b.extend_from_slice(&[p[2], p[1], p[0]]);
                }
            }
        }
        b.resize(start + row, 0);
    }
    std::fs::write(path, b).unwrap();
}

/// A BMP cut short (header whole, pixel rows missing) and one with a
/// broken header: an error naming the file, no output.
#[test]
fn damaged_bmp_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let f = frames(2);
    let mut paths = Vec::new();
    for (k, im) in f.iter().enumerate() {
        let v: Vec<u8> = scaled(im, 250.0).iter().map(|&x| x as u8).collect();
        let p = dir.path().join(format!("g{k}.bmp"));
        write_bmp(&p, 96, 80, Bmp::Grey8(&v));
        paths.push(p);
    }
    let whole = std::fs::read(&paths[1]).unwrap();
    for (name, bytes) in [
        ("short.bmp", whole[..whole.len() / 2].to_vec()),
        ("header.bmp", whole[..30].to_vec()),
    ] {
        let bad = dir.path().join(name);
        std::fs::write(&bad, bytes).unwrap();
        let out = dir.path().join(format!("out_{name}"));
        let r = run(&[path_str(&paths[0]), path_str(&bad)], &out);
        let err = String::from_utf8_lossy(&r.stderr);
        assert!(!r.status.success(), "{name}: {err}");
        assert!(err.contains(name) && err.contains("BMP"), "{name}: {err}");
        assert!(!out.exists(), "{name}: output left behind");
    }
}

#[test]
fn bmp_pair_grey_and_colour() {
    let dir = tempfile::tempdir().unwrap();
    let f = frames(2);
    let mut grey = Vec::new();
    let mut colour = Vec::new();
    for (k, im) in f.iter().enumerate() {
        let v: Vec<u8> = scaled(im, 250.0).iter().map(|&x| x as u8).collect();
        let p = dir.path().join(format!("g{k}.bmp"));
        write_bmp(&p, 96, 80, Bmp::Grey8(&v));
        grey.push(p);
        // Blue at half the brightness: a colour image, not a grey one.
        let rgb: Vec<u8> = v.iter().flat_map(|&x| [x, x, x / 2]).collect();
        let p = dir.path().join(format!("c{k}.bmp"));
        write_bmp(&p, 96, 80, Bmp::Rgb24(&rgb));
        colour.push(p);
    }
    let out = dir.path().join("g");
    let r = run(&[path_str(&grey[0]), path_str(&grey[1])], &out);
    assert_shift(&r, &out, 1);
    assert!(!String::from_utf8_lossy(&r.stderr).contains("colour"));
    let out = dir.path().join("c");
    let r = run(&[path_str(&colour[0]), path_str(&colour[1])], &out);
    assert_shift(&r, &out, 1);
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(err.contains("c0.bmp is a colour image"), "{err}");
}

/// A minimal little-endian TIFF: one uncompressed strip of 8-bit indices
/// and a grey colour map (photometric interpretation 3, palette).
fn write_palette_tiff(path: &Path, w: u32, h: u32, idx: &[u8]) {
    let mut b: Vec<u8> = Vec::new();
    b.extend_from_slice(b"II*\0");
    let map_off = 8u32;
    let data_off = map_off + 3 * 256 * 2;
    let ifd_off = data_off + idx.len() as u32;
    b.extend_from_slice(&ifd_off.to_le_bytes());
    for _ in 0..3 {
        for k in 0..256u32 {
            b.extend_from_slice(&((k * 257) as u16).to_le_bytes());
        }
    }
    b.extend_from_slice(idx);
    // (tag, type, count, value): 3 = SHORT, 4 = LONG.
    let entries: [(u16, u16, u32, u32); 10] = [
        (256, 4, 1, w),
        (257, 4, 1, h),
        (258, 3, 1, 8),
        (259, 3, 1, 1),
        (262, 3, 1, 3),
        (273, 4, 1, data_off),
        (277, 3, 1, 1),
        (278, 4, 1, h),
        (279, 4, 1, idx.len() as u32),
        (320, 3, 3 * 256, map_off),
    ];
    b.extend_from_slice(&(entries.len() as u16).to_le_bytes());
    for (tag, ty, count, value) in entries {
        b.extend_from_slice(&tag.to_le_bytes());
        b.extend_from_slice(&ty.to_le_bytes());
        b.extend_from_slice(&count.to_le_bytes());
        if ty == 3 && count == 1 {
            b.extend_from_slice(&(value as u16).to_le_bytes());
            b.extend_from_slice(&[0, 0]);
        } else {
            b.extend_from_slice(&value.to_le_bytes());
        }
    }
    b.extend_from_slice(&0u32.to_le_bytes());
    std::fs::write(path, b).unwrap();
}

#[test]
fn palette_tiff_pair() {
    let dir = tempfile::tempdir().unwrap();
    let mut paths = Vec::new();
    for (k, im) in frames(2).iter().enumerate() {
        let v: Vec<u8> = scaled(im, 250.0).iter().map(|&x| x as u8).collect();
        let p = dir.path().join(format!("p{k}.tif"));
        write_palette_tiff(&p, 96, 80, &v);
        paths.push(p);
    }
    let out = dir.path().join("o");
    let r = run(&[path_str(&paths[0]), path_str(&paths[1])], &out);
    assert_shift(&r, &out, 1);
    assert!(!String::from_utf8_lossy(&r.stderr).contains("colour"));
}

#[test]
fn sixteen_bit_tiff_stack_gives_one_frame_per_page() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("stack.tif");
    {
        let f = std::fs::File::create(&p).unwrap();
        let mut enc = tiff::encoder::TiffEncoder::new(f).unwrap();
        for im in frames(4) {
            let v: Vec<u16> = scaled(&im, 60000.0).iter().map(|&x| x as u16).collect();
            enc.write_image::<tiff::encoder::colortype::Gray16>(96, 80, &v)
                .unwrap();
        }
    }
    // Pages 1-2, 2-3, 3-4.
    let out = dir.path().join("seq");
    assert_shift(&run(&[path_str(&p), "--sequence"], &out), &out, 3);
    // Pairs 1-2, 3-4: vectors_00000 and vectors_00002.
    let out = dir.path().join("pairs");
    let r = run(&[path_str(&p)], &out);
    assert!(r.status.success());
    assert!(out.join("vectors_00002.csv").exists());
    assert!(!out.join("vectors_00001.csv").exists());
}

/// Eleven frames `frame0.png` … `frame10.png`: a pattern and a folder are
/// read in natural order (in plain text order `frame10` would follow
/// `frame1` and its pair would show ten shifts at once).
#[test]
fn png_pattern_and_folder_in_natural_order() {
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("seq");
    std::fs::create_dir(&seq).unwrap();
    for (k, im) in frames(11).iter().enumerate() {
        save_png16(&seq.join(format!("frame{k}.png")), im, 20000.0).unwrap();
    }
    std::fs::write(seq.join("notes.txt"), "not an image").unwrap();
    let pattern: PathBuf = seq.join("frame*.png");
    let out = dir.path().join("glob");
    assert_shift(&run(&[path_str(&pattern), "--sequence"], &out), &out, 10);
    let out = dir.path().join("dir");
    assert_shift(&run(&[path_str(&seq), "--sequence"], &out), &out, 10);
    let none = seq.join("nothing*.png");
    let r = run(&[path_str(&none)], &dir.path().join("none"));
    assert!(!r.status.success());
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(
        err.contains("no file matches") && err.contains("nothing*.png"),
        "{err}"
    );
}
