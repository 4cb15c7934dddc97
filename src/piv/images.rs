//! Reading ordinary PIV images as grey [`Image`]s: PNG (8/16 bit, palette),
//! TIFF (8/16/32-bit grey, RGB, palette; every page of a multi-page stack),
//! BMP, and folders or wildcard patterns of such files in natural order.
//!
//! Colour images are reduced to their luminance (Rec. 601 weights, alpha
//! dropped): PIV recordings are grey, and an RGB export of a grey image has
//! equal channels, so its luminance is the grey value. Values keep their raw
//! scale (0–255 or 0–65535); correlation normalises anyway.

use std::cmp::Ordering;
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use super::Image;
use crate::error::{Error, Result};

/// Luminance weights (Rec. 601) of red, green and blue.
const LUMA: [f32; 3] = [0.299, 0.587, 0.114];

/// The frames of one image file: one for an ordinary image, one per page
/// of a multi-page TIFF.
#[derive(Debug, Clone, PartialEq)]
pub struct Frames {
    /// The frames in file order (TIFF pages), grey or luminance.
    pub frames: Vec<Image>,
    /// The file held colour (channels that differ somewhere), reduced to
    /// luminance.
    pub colour: bool,
}

/// Load the first frame of an image file (see [`load_frames`]).
#[cfg(feature = "testkit")]
pub(crate) fn load_image(path: &Path) -> Result<Image> {
    let mut f = load_frames(path)?;
    // `load_frames` never returns an empty list.
    Ok(f.frames.swap_remove(0))
}

/// Load every frame of a PNG, TIFF or BMP file, chosen by content (magic
/// bytes), as grey images.
pub(crate) fn load_frames(path: &Path) -> Result<Frames> {
    let head = {
        let mut f = File::open(path).map_err(|e| Error::io(path, e))?;
        let mut b = [0u8; 8];
        let n = f.read(&mut b).map_err(|e| Error::io(path, e))?;
        b[..n].to_vec()
    };
    if head.starts_with(b"\x89PNG") {
        load_png(path).map(|(img, colour)| Frames {
            frames: vec![img],
            colour,
        })
    } else if head.starts_with(b"II*\0")
        || head.starts_with(b"MM\0*")
        || head.starts_with(b"II+\0")
        || head.starts_with(b"MM\0+")
    {
        load_tiff(path)
    } else if head.starts_with(b"BM") {
        load_bmp(path)
    } else {
        Err(Error::corrupt(
            path,
            0,
            "not a PNG, TIFF or BMP image (convert other formats to PNG or TIFF first)",
        ))
    }
}

/// The image files named by `inputs`, in order: a file stands for itself,
/// a folder for its image files (`.png`, `.tif`, `.tiff`, `.bmp`) and a
/// pattern with `*` or `?` in its file name for the matching files; the
/// files of a folder or pattern are in natural order (`frame2` before
/// `frame10`).
pub(crate) fn expand_inputs(inputs: &[PathBuf]) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for p in inputs {
        if p.is_dir() {
            let mut v = list_dir(p, &|name| {
                let l = name.to_ascii_lowercase();
                [".png", ".tif", ".tiff", ".bmp"]
                    .iter()
                    .any(|e| l.ends_with(e))
            })?;
            if v.is_empty() {
                return Err(Error::param(
                    "images",
                    format!("{}: folder holds no PNG, TIFF or BMP file", p.display()),
                ));
            }
            v.sort_by(|a, b| natural_cmp(&a.to_string_lossy(), &b.to_string_lossy()));
            out.extend(v);
            continue;
        }
        let name = p
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        if !p.exists() && (name.contains('*') || name.contains('?')) {
            let dir = match p.parent() {
                Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
                _ => PathBuf::from("."),
            };
            let mut v = list_dir(&dir, &|n| wildcard_match(&name, n))?;
            if v.is_empty() {
                return Err(Error::param(
                    "images",
                    format!("no file matches {}", p.display()),
                ));
            }
            v.sort_by(|a, b| natural_cmp(&a.to_string_lossy(), &b.to_string_lossy()));
            out.extend(v);
            continue;
        }
        out.push(p.clone());
    }
    Ok(out)
}

/// The files (not folders) of `dir` whose name passes `keep`.
fn list_dir(dir: &Path, keep: &dyn Fn(&str) -> bool) -> Result<Vec<PathBuf>> {
    let mut v = Vec::new();
    for e in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))? {
        let e = e.map_err(|e| Error::io(dir, e))?;
        let path = e.path();
        if path.is_file() && keep(&e.file_name().to_string_lossy()) {
            v.push(path);
        }
    }
    Ok(v)
}

/// `name` matches `pattern`, where `*` stands for any run of characters
/// and `?` for one character.
pub(crate) fn wildcard_match(pattern: &str, name: &str) -> bool {
    let p: Vec<char> = pattern.chars().collect();
    let n: Vec<char> = name.chars().collect();
    let (mut i, mut j) = (0usize, 0usize);
    let mut star: Option<(usize, usize)> = None;
    while j < n.len() {
        if i < p.len() && (p[i] == '?' || p[i] == n[j]) {
            i += 1;
            j += 1;
        } else if i < p.len() && p[i] == '*' {
            star = Some((i, j));
            i += 1;
        } else if let Some((si, sj)) = star {
            i = si + 1;
            j = sj + 1;
            star = Some((si, sj + 1));
        } else {
            return false;
        }
    }
    while i < p.len() && p[i] == '*' {
        i += 1;
    }
    i == p.len()
}

/// Natural order of names: runs of digits compare as numbers (`frame2`
/// before `frame10`), everything else character by character.
pub(crate) fn natural_cmp(a: &str, b: &str) -> Ordering {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    let (mut i, mut j) = (0usize, 0usize);
    while i < a.len() && j < b.len() {
        if a[i].is_ascii_digit() && b[j].is_ascii_digit() {
            let (si, sj) = (i, j);
            while i < a.len() && a[i].is_ascii_digit() {
                i += 1;
            }
            while j < b.len() && b[j].is_ascii_digit() {
                j += 1;
            }
            let da = trim_zeros(&a[si..i]);
            let db = trim_zeros(&b[sj..j]);
            let o = da.len().cmp(&db.len()).then_with(|| da.cmp(db));
            if o != Ordering::Equal {
                return o;
            }
        } else {
            if a[i] != b[j] {
                return a[i].cmp(&b[j]);
            }
            i += 1;
            j += 1;
        }
    }
    (a.len() - i).cmp(&(b.len() - j)).then_with(|| a.cmp(b))
}

fn trim_zeros(d: &[u8]) -> &[u8] {
    let k = d.iter().position(|&c| c != b'0').unwrap_or(d.len());
    &d[k..]
}

/// Grey image from interleaved samples of `ch` channels (the last one
/// alpha when `alpha`); colour is reduced to luminance. Also says whether
/// the colour channels differed anywhere.
fn grey_from_channels(
    path: &Path,
    w: usize,
    h: usize,
    ch: usize,
    alpha: bool,
    samples: impl Iterator<Item = f32>,
) -> Result<(Image, bool)> {
    let short = |n: usize| {
        Error::corrupt(
            path,
            0,
            format!("image data holds {n} pixels, header says {w}x{h}"),
        )
    };
    let colour = if alpha { ch - 1 } else { ch };
    let mut data = Vec::with_capacity(w * h);
    if colour == 1 {
        // Grey: the samples are the pixels (the common case, no per-sample
        // channel bookkeeping).
        data.extend(samples.step_by(ch).take(w * h + 1));
        if data.len() != w * h {
            return Err(short(data.len()));
        }
        return Ok((
            Image {
                width: w,
                height: h,
                data,
            },
            false,
        ));
    }
    let mut px = [0.0f32; 4];
    let mut differ = false;
    for (i, s) in samples.enumerate() {
        let c = i % ch;
        px[c.min(3)] = s;
        if c == ch - 1 {
            let v = if colour >= 3 {
                differ |= px[0] != px[1] || px[1] != px[2];
                LUMA[0] * px[0] + LUMA[1] * px[1] + LUMA[2] * px[2]
            } else {
                px[..colour].iter().sum::<f32>() / colour as f32
            };
            data.push(v);
        }
    }
    if data.len() != w * h {
        return Err(short(data.len()));
    }
    Ok((
        Image {
            width: w,
            height: h,
            data,
        },
        differ,
    ))
}

fn load_png(path: &Path) -> Result<(Image, bool)> {
    let f = File::open(path).map_err(|e| Error::io(path, e))?;
    let mut dec = png::Decoder::new(BufReader::new(f));
    // Palette and sub-byte depths expand to 8 bit; 16 bit stays 16 bit.
    dec.set_transformations(png::Transformations::EXPAND);
    let mut reader = dec
        .read_info()
        .map_err(|e| Error::corrupt(path, 0, format!("PNG header: {e}")))?;
    let mut buf = vec![0u8; reader.output_buffer_size()];
    let info = reader
        .next_frame(&mut buf)
        .map_err(|e| Error::corrupt(path, 0, format!("PNG data: {e}")))?;
    let (w, h) = (info.width as usize, info.height as usize);
    let (ch, alpha) = match info.color_type {
        png::ColorType::Grayscale => (1, false),
        png::ColorType::GrayscaleAlpha => (2, true),
        png::ColorType::Rgb => (3, false),
        png::ColorType::Rgba => (4, true),
        png::ColorType::Indexed => (3, false),
    };
    let bytes = &buf[..info.buffer_size()];
    let line = info.line_size;
    match info.bit_depth {
        png::BitDepth::Sixteen if ch == 1 => {
            // Grey 16 bit, the usual PIV export: rows straight into floats.
            let mut data = Vec::with_capacity(w * h);
            for y in 0..h {
                let row = &bytes[y * line..y * line + w * 2];
                data.extend(
                    row.chunks_exact(2)
                        .map(|b| u16::from_be_bytes([b[0], b[1]]) as f32),
                );
            }
            Ok((
                Image {
                    width: w,
                    height: h,
                    data,
                },
                false,
            ))
        }
        png::BitDepth::Sixteen => {
            let it = (0..h).flat_map(|y| {
                let row = &bytes[y * line..y * line + w * ch * 2];
                row.chunks_exact(2)
                    .map(|b| u16::from_be_bytes([b[0], b[1]]) as f32)
            });
            grey_from_channels(path, w, h, ch, alpha, it)
        }
        _ => {
            let it =
                (0..h).flat_map(|y| bytes[y * line..y * line + w * ch].iter().map(|&b| b as f32));
            grey_from_channels(path, w, h, ch, alpha, it)
        }
    }
}

/// A BMP file (1/4/8-bit palette, RLE4/RLE8, 16/24/32-bit) through
/// `tinybmp`, whose pixels come as RGB: grey when the three channels agree
/// everywhere (a grey palette), a colour image otherwise.
fn load_bmp(path: &Path) -> Result<Frames> {
    use embedded_graphics::pixelcolor::{Rgb888, RgbColor};
    use embedded_graphics::prelude::{OriginDimensions, Pixel};
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let bmp = tinybmp::Bmp::<Rgb888>::from_slice(&bytes)
        .map_err(|e| Error::corrupt(path, 0, format!("BMP: {e:?}")))?;
    let size = bmp.size();
    let (w, h) = (size.width as usize, size.height as usize);
    let mut rgb = vec![0.0f32; 3 * w * h];
    let mut seen = 0usize;
    for Pixel(p, c) in bmp.pixels() {
        let (x, y) = (p.x as usize, p.y as usize);
        if p.x < 0 || p.y < 0 || x >= w || y >= h {
            continue;
        }
        let k = 3 * (y * w + x);
        rgb[k] = f32::from(c.r());
        rgb[k + 1] = f32::from(c.g());
        rgb[k + 2] = f32::from(c.b());
        seen += 1;
    }
    if seen != w * h {
        return Err(Error::corrupt(
            path,
            0,
            format!("image data holds {seen} pixels, header says {w}x{h}"),
        ));
    }
    let (img, colour) = grey_from_channels(path, w, h, 3, false, rgb.into_iter())?;
    Ok(Frames {
        frames: vec![img],
        colour,
    })
}

/// Every page of a TIFF file.
fn load_tiff(path: &Path) -> Result<Frames> {
    use tiff::decoder::Decoder;
    let f = File::open(path).map_err(|e| Error::io(path, e))?;
    let bad = |e: tiff::TiffError| Error::corrupt(path, 0, format!("TIFF: {e}"));
    let mut dec = Decoder::new(BufReader::new(f)).map_err(bad)?;
    let mut frames = Vec::new();
    let mut colour = false;
    loop {
        let page = frames.len();
        let bad_page = |e: Error| {
            if page == 0 {
                e
            } else {
                Error::corrupt(path, 0, format!("page {}: {e}", page + 1))
            }
        };
        let (img, c) = tiff_page(path, &mut dec).map_err(bad_page)?;
        colour |= c;
        frames.push(img);
        if !dec.more_images() {
            break;
        }
        dec.next_image().map_err(bad)?;
    }
    Ok(Frames { frames, colour })
}

fn tiff_page<R: Read + Seek>(
    path: &Path,
    dec: &mut tiff::decoder::Decoder<R>,
) -> Result<(Image, bool)> {
    use tiff::decoder::DecodingResult;
    use tiff::tags::Tag;
    let bad = |e: tiff::TiffError| Error::corrupt(path, 0, format!("TIFF: {e}"));
    let (w, h) = dec.dimensions().map_err(bad)?;
    let (w, h) = (w as usize, h as usize);
    let photometric = dec
        .find_tag_unsigned::<u16>(Tag::PhotometricInterpretation)
        .map_err(bad)?;
    if photometric == Some(3) {
        return tiff_palette_page(path, dec, w, h);
    }
    let (ch, alpha) = match dec.colortype().map_err(bad)? {
        tiff::ColorType::Gray(_) => (1, false),
        tiff::ColorType::GrayA(_) => (2, true),
        tiff::ColorType::RGB(_) => (3, false),
        tiff::ColorType::RGBA(_) => (4, true),
        other => {
            return Err(Error::corrupt(
                path,
                0,
                format!("TIFF colour type {other:?} not supported (grey, RGB or palette)"),
            ))
        }
    };
    match dec.read_image().map_err(bad)? {
        DecodingResult::U8(v) => {
            grey_from_channels(path, w, h, ch, alpha, v.into_iter().map(|x| x as f32))
        }
        DecodingResult::U16(v) => {
            grey_from_channels(path, w, h, ch, alpha, v.into_iter().map(|x| x as f32))
        }
        DecodingResult::U32(v) => {
            grey_from_channels(path, w, h, ch, alpha, v.into_iter().map(|x| x as f32))
        }
        DecodingResult::F32(v) => grey_from_channels(path, w, h, ch, alpha, v.into_iter()),
        DecodingResult::F64(v) => {
            grey_from_channels(path, w, h, ch, alpha, v.into_iter().map(|x| x as f32))
        }
        _ => Err(Error::corrupt(
            path,
            0,
            "TIFF sample type not supported (8/16/32-bit unsigned or float)",
        )),
    }
}

/// A palette (colour-mapped) TIFF page: strips of 1/2/4/8-bit indices,
/// uncompressed, LZW, Deflate or PackBits, mapped through the colour map
/// to luminance on the 0–255 scale.
fn tiff_palette_page<R: Read + Seek>(
    path: &Path,
    dec: &mut tiff::decoder::Decoder<R>,
    w: usize,
    h: usize,
) -> Result<(Image, bool)> {
    use tiff::tags::Tag;
    let bad = |e: tiff::TiffError| Error::corrupt(path, 0, format!("TIFF: {e}"));
    let unsupported = |what: String| Error::corrupt(path, 0, format!("palette TIFF: {what}"));
    let bits = dec
        .find_tag_unsigned::<u16>(Tag::BitsPerSample)
        .map_err(bad)?
        .unwrap_or(1) as usize;
    if ![1, 2, 4, 8].contains(&bits) {
        return Err(unsupported(format!("{bits}-bit indices not supported")));
    }
    let map = dec
        .find_tag_unsigned_vec::<u16>(Tag::ColorMap)
        .map_err(bad)?
        .ok_or_else(|| unsupported("no colour map".into()))?;
    let n_colours = 1usize << bits;
    if map.len() != 3 * n_colours {
        return Err(unsupported(format!(
            "colour map holds {} values, {}-bit indices need {}",
            map.len(),
            bits,
            3 * n_colours
        )));
    }
    let mut lut = Vec::with_capacity(n_colours);
    let mut colour = false;
    for k in 0..n_colours {
        let (r, g, b) = (map[k], map[n_colours + k], map[2 * n_colours + k]);
        colour |= r != g || g != b;
        lut.push((LUMA[0] * r as f32 + LUMA[1] * g as f32 + LUMA[2] * b as f32) / 257.0);
    }
    if dec
        .find_tag_unsigned::<u16>(Tag::SamplesPerPixel)
        .map_err(bad)?
        .unwrap_or(1)
        != 1
    {
        return Err(unsupported("more than one sample per pixel".into()));
    }
    if dec.find_tag(Tag::TileOffsets).map_err(bad)?.is_some() {
        return Err(unsupported(
            "tiled layout not supported (strips only)".into(),
        ));
    }
    if dec
        .find_tag_unsigned::<u16>(Tag::Predictor)
        .map_err(bad)?
        .unwrap_or(1)
        != 1
    {
        return Err(unsupported("predictor not supported".into()));
    }
    let compression = dec
        .find_tag_unsigned::<u16>(Tag::Compression)
        .map_err(bad)?
        .unwrap_or(1);
    let offsets = dec
        .find_tag_unsigned_vec::<u64>(Tag::StripOffsets)
        .map_err(bad)?
        .ok_or_else(|| unsupported("no strip offsets".into()))?;
    let counts = dec
        .find_tag_unsigned_vec::<u64>(Tag::StripByteCounts)
        .map_err(bad)?
        .ok_or_else(|| unsupported("no strip byte counts".into()))?;
    let rows_per_strip = dec
        .find_tag_unsigned::<u64>(Tag::RowsPerStrip)
        .map_err(bad)?
        .unwrap_or(h as u64)
        .clamp(1, h.max(1) as u64) as usize;
    if offsets.len() != counts.len() || offsets.len() < h.div_ceil(rows_per_strip) {
        return Err(unsupported(format!(
            "{} strips for {} rows of {} per strip",
            offsets.len(),
            h,
            rows_per_strip
        )));
    }
    let row_bytes = (w * bits).div_ceil(8);
    let mut file = File::open(path).map_err(|e| Error::io(path, e))?;
    let len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    let mut data = Vec::with_capacity(w * h);
    for (s, (&off, &cnt)) in offsets.iter().zip(&counts).enumerate() {
        let rows = rows_per_strip.min(h.saturating_sub(s * rows_per_strip));
        if rows == 0 {
            break;
        }
        if off.checked_add(cnt).is_none_or(|end| end > len) {
            return Err(Error::corrupt(
                path,
                off,
                format!("strip {s} runs past the end of the file"),
            ));
        }
        let mut raw = vec![0u8; cnt as usize];
        file.seek(SeekFrom::Start(off))
            .and_then(|_| file.read_exact(&mut raw))
            .map_err(|e| Error::io(path, e))?;
        let need = rows * row_bytes;
        let plain = match compression {
            1 => raw,
            5 => weezl::decode::Decoder::with_tiff_size_switch(weezl::BitOrder::Msb, 8)
                .decode(&raw)
                .map_err(|e| Error::corrupt(path, off, format!("LZW strip {s}: {e}")))?,
            8 | 32946 => {
                let mut v = Vec::with_capacity(need);
                flate2::read::ZlibDecoder::new(&raw[..])
                    .read_to_end(&mut v)
                    .map_err(|e| Error::corrupt(path, off, format!("Deflate strip {s}: {e}")))?;
                v
            }
            32773 => unpack_bits(&raw, need),
            c => return Err(unsupported(format!("compression {c} not supported"))),
        };
        if plain.len() < need {
            return Err(Error::corrupt(
                path,
                off,
                format!(
                    "strip {s} holds {} bytes, {rows} rows need {need}",
                    plain.len()
                ),
            ));
        }
        for r in 0..rows {
            let row = &plain[r * row_bytes..(r + 1) * row_bytes];
            for x in 0..w {
                let bit = x * bits;
                let byte = row[bit / 8];
                let idx = (byte >> (8 - bits - bit % 8)) as usize & (n_colours - 1);
                data.push(lut[idx]);
            }
        }
    }
    Ok((
        Image {
            width: w,
            height: h,
            data,
        },
        colour,
    ))
}

/// PackBits decoding, up to `need` bytes.
fn unpack_bits(src: &[u8], need: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(need);
    let mut i = 0;
    while i < src.len() && out.len() < need {
        let n = src[i] as i8;
        i += 1;
        if n >= 0 {
            let k = (n as usize + 1).min(src.len() - i);
            out.extend_from_slice(&src[i..i + k]);
            i += k;
        } else if n != -128 {
            if let Some(&b) = src.get(i) {
                out.extend(std::iter::repeat_n(b, (1 - n as isize) as usize));
                i += 1;
            }
        }
    }
    out
}

/// Write a grey image as a 16-bit PNG (values clamped to 0–65535), through
/// an atomic file. Used to export synthetic images for peer comparison.
#[ebptv_macros::testkit]
pub(crate) fn save_png16(path: &Path, img: &Image, scale: f32) -> Result<()> {
    let mut bytes = Vec::with_capacity(img.data.len() * 2);
    for &v in &img.data {
        let q = (v * scale).round().clamp(0.0, 65535.0) as u16;
        bytes.extend_from_slice(&q.to_be_bytes());
    }
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, img.width as u32, img.height as u32);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Sixteen);
        let mut wr = enc
            .write_header()
            .map_err(|e| Error::param("output", format!("{}: {e}", path.display())))?;
        wr.write_image_data(&bytes)
            .map_err(|e| Error::param("output", format!("{}: {e}", path.display())))?;
    }
    crate::io::atomic::AtomicFile::write_all_to(path, &out)
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn png16_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.png");
        let mut img = Image::zeros(7, 5);
        for (i, v) in img.data.iter_mut().enumerate() {
            *v = (i * 1000) as f32;
        }
        save_png16(&p, &img, 1.0).unwrap();
        let back = load_image(&p).unwrap();
        assert_eq!(back, img);
    }

    #[ebptv_macros::unit_test]
    fn tiff_round_trip_8bit() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.tif");
        let data: Vec<u8> = (0..6 * 4).map(|i| (i * 10) as u8).collect();
        {
            let f = File::create(&p).unwrap();
            let mut enc = tiff::encoder::TiffEncoder::new(f).unwrap();
            enc.write_image::<tiff::encoder::colortype::Gray8>(6, 4, &data)
                .unwrap();
        }
        let img = load_image(&p).unwrap();
        assert_eq!((img.width, img.height), (6, 4));
        assert_eq!(img.get(5, 3), 230.0);
    }

    #[ebptv_macros::unit_test]
    fn garbage_is_a_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.png");
        std::fs::write(&p, b"GIF89a not an image").unwrap();
        let e = load_image(&p).unwrap_err().to_string();
        assert!(
            e.contains("x.png") && e.contains("not a PNG, TIFF or BMP"),
            "{e}"
        );
        std::fs::write(&p, b"BM truncated").unwrap();
        let e = load_image(&p).unwrap_err().to_string();
        assert!(e.contains("x.png"), "{e}");
        std::fs::write(&p, b"\x89PNG\r\n\x1a\ntruncated").unwrap();
        assert!(load_image(&p).is_err());
    }

    #[ebptv_macros::unit_test]
    fn natural_order_and_wildcards() {
        let mut v = vec!["f10.png", "f2.png", "f1.png", "f02b.png", "e9.png"];
        v.sort_by(|a, b| natural_cmp(a, b));
        assert_eq!(v, ["e9.png", "f1.png", "f2.png", "f02b.png", "f10.png"]);
        assert!(wildcard_match("frame*.png", "frame12.png"));
        assert!(wildcard_match("f?.t*f", "f1.tiff"));
        assert!(!wildcard_match("frame*.png", "frame12.png.txt"));
        assert!(!wildcard_match("f?.png", "f12.png"));
    }

    #[ebptv_macros::unit_test]
    fn packbits_runs_and_literals() {
        // 2 literals, then a run of 3.
        assert_eq!(unpack_bits(&[1, 7, 8, 0xfe, 9], 5), [7, 8, 9, 9, 9]);
    }
}
