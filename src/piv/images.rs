//! Reading ordinary PIV images (8/16-bit PNG, TIFF) as grey [`Image`]s.
//!
//! Colour images are reduced to their channel mean (alpha dropped): PIV
//! recordings are grey, and an RGB export of a grey image has equal
//! channels. Values keep their raw scale (0–255 or 0–65535); correlation
//! normalises anyway.

use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use super::Image;
use crate::error::{Error, Result};

/// Load a PNG or TIFF image, chosen by content (magic bytes).
pub fn load_image(path: &Path) -> Result<Image> {
    let head = {
        use std::io::Read;
        let mut f = File::open(path).map_err(|e| Error::io(path, e))?;
        let mut b = [0u8; 8];
        let n = f.read(&mut b).map_err(|e| Error::io(path, e))?;
        b[..n].to_vec()
    };
    if head.starts_with(b"\x89PNG") {
        load_png(path)
    } else if head.starts_with(b"II*\0")
        || head.starts_with(b"MM\0*")
        || head.starts_with(b"II+\0")
        || head.starts_with(b"MM\0+")
    {
        load_tiff(path)
    } else {
        Err(Error::corrupt(
            path,
            0,
            "not a PNG or TIFF image (convert other formats, e.g. BMP, to PNG first)",
        ))
    }
}

fn grey_from_channels(
    path: &Path,
    w: usize,
    h: usize,
    ch: usize,
    alpha: bool,
    samples: impl Iterator<Item = f32>,
) -> Result<Image> {
    if ch == 1 {
        // Grey: the samples are the pixels (the common case, no per-sample
        // channel bookkeeping).
        let mut data = Vec::with_capacity(w * h);
        data.extend(samples.take(w * h + 1));
        if data.len() != w * h {
            return Err(Error::corrupt(
                path,
                0,
                format!(
                    "image data holds {} pixels, header says {w}x{h}",
                    data.len()
                ),
            ));
        }
        return Ok(Image {
            width: w,
            height: h,
            data,
        });
    }
    let colour = if alpha { ch - 1 } else { ch };
    let mut data = Vec::with_capacity(w * h);
    let mut acc = 0.0f32;
    let mut n = 0usize;
    for (i, s) in samples.enumerate() {
        let c = i % ch;
        if c < colour {
            acc += s;
        }
        if c == ch - 1 {
            data.push(acc / colour as f32);
            acc = 0.0;
            n += 1;
        }
    }
    if n != w * h {
        return Err(Error::corrupt(
            path,
            0,
            format!("image data holds {n} pixels, header says {w}x{h}"),
        ));
    }
    Ok(Image {
        width: w,
        height: h,
        data,
    })
}

fn load_png(path: &Path) -> Result<Image> {
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
            Ok(Image {
                width: w,
                height: h,
                data,
            })
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

fn load_tiff(path: &Path) -> Result<Image> {
    use tiff::decoder::{Decoder, DecodingResult};
    let f = File::open(path).map_err(|e| Error::io(path, e))?;
    let bad = |e: tiff::TiffError| Error::corrupt(path, 0, format!("TIFF: {e}"));
    let mut dec = Decoder::new(BufReader::new(f)).map_err(bad)?;
    let (w, h) = dec.dimensions().map_err(bad)?;
    let (w, h) = (w as usize, h as usize);
    let (ch, alpha) = match dec.colortype().map_err(bad)? {
        tiff::ColorType::Gray(_) => (1, false),
        tiff::ColorType::GrayA(_) => (2, true),
        tiff::ColorType::RGB(_) => (3, false),
        tiff::ColorType::RGBA(_) => (4, true),
        other => {
            return Err(Error::corrupt(
                path,
                0,
                format!("TIFF colour type {other:?} not supported (grey or RGB)"),
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

/// Write a grey image as a 16-bit PNG (values clamped to 0–65535), through
/// an atomic file. Used to export synthetic images for peer comparison.
pub fn save_png16(path: &Path, img: &Image, scale: f32) -> Result<()> {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
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

    #[test]
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

    #[test]
    fn garbage_is_a_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.png");
        std::fs::write(&p, b"BM not an image").unwrap();
        let e = load_image(&p).unwrap_err().to_string();
        assert!(
            e.contains("x.png") && e.contains("not a PNG or TIFF"),
            "{e}"
        );
        std::fs::write(&p, b"\x89PNG\r\n\x1a\ntruncated").unwrap();
        assert!(load_image(&p).is_err());
    }
}
