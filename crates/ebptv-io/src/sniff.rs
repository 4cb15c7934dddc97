//! Format detection: content first, extension as the fallback.
//!
//! Extensions lie (a `.raw` may hold EVT 2.0 or EVT 3.0; files get renamed),
//! so `detect_format` reads the first bytes of the file and looks for what
//! each format puts there:
//! - AEDAT 4.0: the magic `#!AER-DAT4.0`; Event Stream: `Event Stream`;
//!   NumPy: `\x93NUMPY` (an ebptv *output* format, reported as such).
//! - Prophesee RAW vs DAT: both start with `% ` header lines. RAW headers
//!   name the encoding (`% format`, `% evt`) or a `% system_ID` it can be
//!   inferred from; DAT headers (openeb's `DatWriter`) have `% Version` and
//!   are followed by two bytes, the event type (0x00, 0x0C, 0x0E) and the
//!   record size (8).
//! - CSV: printable text whose first line is comma-separated names or
//!   numbers.
//!
//! Only when content says nothing do we trust the extension; a file neither
//! recognises is an [`Error::UnknownFormat`] that says what the file starts
//! with (e.g. "starts with a PNG signature").

use std::fs::File;
use std::io::Read;
use std::path::Path;

use crate::error::{Error, Result};
use crate::raw_header::{interpret, parse_percent_header, MAX_HEADER_BYTES};
use crate::Format;

/// Bytes read to sniff a file. Enough for any RAW/DAT header in practice.
const SNIFF_BYTES: u64 = MAX_HEADER_BYTES as u64;

/// Detect the format of the file at `path` from its content, then its
/// extension.
pub fn detect_format(path: &Path) -> Result<Format> {
    let f = File::open(path).map_err(|e| Error::io(path, e))?;
    let mut head = Vec::new();
    f.take(SNIFF_BYTES)
        .read_to_end(&mut head)
        .map_err(|e| Error::io(path, e))?;
    detect_from_bytes(path, &head)
}

/// [`detect_format`] on the first bytes of a file (`path` for the extension
/// fallback and the error message).
pub(crate) fn detect_from_bytes(path: &Path, head: &[u8]) -> Result<Format> {
    match sniff_content(head) {
        Sniffed::Format(f) => return Ok(f),
        Sniffed::Nothing => {}
        Sniffed::Foreign(what) => {
            return Err(Error::UnknownFormat {
                path: path.to_path_buf(),
                why: format!("{what}; not event data"),
            })
        }
    }
    if let Some(f) = format_from_extension(path) {
        // An empty file or one with no recognisable content: the extension
        // is the only clue left; the reader will report what is wrong.
        return Ok(f);
    }
    Err(Error::UnknownFormat {
        path: path.to_path_buf(),
        why: if head.is_empty() {
            "the file is empty and its extension names no known format".into()
        } else {
            format!(
                "{} and its extension names no known format",
                describe_start(head)
            )
        },
    })
}

/// Format by extension: `.raw` = EVT 3.0 (the usual case; content sniffing
/// tells EVT 2.0 / 2.1 apart), `.dat`, `.csv`/`.txt`, `.aedat4`, `.es`,
/// `.npy`, `.evt2`, `.evt21`, `.evt3`.
pub(crate) fn format_from_extension(path: &Path) -> Option<Format> {
    let ext = path.extension()?.to_str()?.to_ascii_lowercase();
    Format::from_name(&ext)
}

enum Sniffed {
    Format(Format),
    /// Content does not decide (e.g. headerless RAW payload, empty file).
    Nothing,
    /// Content is recognisably something other than event data.
    Foreign(String),
}

fn sniff_content(head: &[u8]) -> Sniffed {
    if head.is_empty() {
        return Sniffed::Nothing;
    }
    if head.starts_with(b"#!AER-DAT4") {
        return Sniffed::Format(Format::Aedat4);
    }
    if head.starts_with(b"#!AER-DAT") {
        return Sniffed::Foreign(
            "starts with an AEDAT 2/3 magic (only AEDAT 4.0 is supported)".into(),
        );
    }
    if head.starts_with(b"Event Stream") {
        return Sniffed::Format(Format::Es);
    }
    if head.starts_with(b"\x93NUMPY") {
        return Sniffed::Format(Format::Npy);
    }
    if let Some(what) = foreign_signature(head) {
        return Sniffed::Foreign(what.into());
    }
    if head[0] == b'%' {
        let (entries, off) = parse_percent_header(head);
        if !entries.is_empty() {
            let has = |k: &str| entries.iter().any(|(key, _)| key.eq_ignore_ascii_case(k));
            let raw_words = has("format") || has("evt") || has("geometry");
            let dat_words = has("Version")
                || entries
                    .iter()
                    .any(|(k, v)| k == "Data" && v.starts_with("file"));
            let after = &head[off..];
            let dat_bytes =
                after.len() >= 2 && matches!(after[0], 0x00 | 0x0C | 0x0E) && after[1] == 8;
            if raw_words && !dat_words {
                if let Some(f) = interpret(entries, off as u64).format {
                    return Sniffed::Format(f);
                }
            } else if dat_words || (dat_bytes && !has("system_ID")) {
                return Sniffed::Format(Format::Dat);
            } else if let Some(f) = interpret(entries, off as u64).format {
                // Only `% system_ID`: infer as Prophesee's reader does.
                return Sniffed::Format(f);
            }
            return Sniffed::Nothing;
        }
    }
    if looks_like_csv(head) {
        return Sniffed::Format(Format::Csv);
    }
    Sniffed::Nothing
}

/// Well-known non-event file signatures.
fn foreign_signature(head: &[u8]) -> Option<&'static str> {
    const SIGS: &[(&[u8], &str)] = &[
        (b"\x89PNG\r\n\x1a\n", "starts with a PNG signature"),
        (b"\xff\xd8\xff", "starts with a JPEG signature"),
        (b"GIF8", "starts with a GIF signature"),
        (b"%PDF", "starts with a PDF signature"),
        (b"PK\x03\x04", "starts with a ZIP signature"),
        (b"\x1f\x8b", "starts with a gzip signature"),
        (
            b"\x89HDF\r\n\x1a\n",
            "starts with an HDF5 signature (not supported; convert to RAW)",
        ),
        (b"\x7fELF", "starts with an ELF executable signature"),
        (b"II*\x00", "starts with a TIFF signature"),
        (b"MM\x00*", "starts with a TIFF signature"),
        (b"RIFF", "starts with a RIFF (AVI/WAV) signature"),
        (b"\x28\xb5\x2f\xfd", "starts with a Zstandard signature"),
        (b"BZh", "starts with a bzip2 signature"),
        (b"\xfd7zXZ\x00", "starts with an xz signature"),
    ];
    SIGS.iter()
        .find(|(s, _)| head.starts_with(s))
        .map(|(_, w)| *w)
}

/// Printable text, first line comma/whitespace-separated names or numbers.
fn looks_like_csv(head: &[u8]) -> bool {
    let sample = &head[..head.len().min(4096)];
    if !sample
        .iter()
        .all(|&b| b == b'\n' || b == b'\r' || b == b'\t' || (0x20..0x7f).contains(&b))
    {
        return false;
    }
    let text = std::str::from_utf8(sample).unwrap_or("");
    let Some(first) = text
        .lines()
        .find(|l| !l.trim().is_empty() && !l.starts_with('#'))
    else {
        return false;
    };
    let fields: Vec<&str> = first
        .split([',', ';', '\t', ' '])
        .filter(|f| !f.is_empty())
        .collect();
    fields.len() >= 3
        && fields.iter().all(|f| {
            let f = f.trim().trim_matches('"');
            !f.is_empty()
                && (f.parse::<f64>().is_ok()
                    || f.chars().all(|c| c.is_ascii_alphanumeric() || c == '_'))
        })
}

/// A short human description of a file's first bytes.
fn describe_start(head: &[u8]) -> String {
    let n = head.len().min(8);
    let hex: Vec<String> = head[..n].iter().map(|b| format!("{b:02x}")).collect();
    let printable: String = head[..n]
        .iter()
        .map(|&b| {
            if (0x20..0x7f).contains(&b) {
                b as char
            } else {
                '.'
            }
        })
        .collect();
    format!("starts with bytes {} (\"{}\")", hex.join(" "), printable)
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    fn det(name: &str, bytes: &[u8]) -> Result<Format> {
        detect_from_bytes(Path::new(name), bytes)
    }

    #[ebptv_macros::unit_test]
    fn content_beats_extension() {
        assert_eq!(
            det("a.raw", b"% evt 2.0\n% system_ID 21\n\x00\x00\x00\x80").unwrap(),
            Format::Evt2
        );
        assert_eq!(
            det("a.dat", b"% format EVT3;height=720;width=1280\n% end\n").unwrap(),
            Format::Evt3
        );
        assert_eq!(
            det("a.raw", b"% format EVT21;endianness=legacy\n% end\n").unwrap(),
            Format::Evt21
        );
        assert_eq!(
            det("x.bin", b"% system_ID 48\n\x00\x80").unwrap(),
            Format::Evt3
        );
        assert_eq!(
            det("x.raw", b"#!AER-DAT4.0\r\n\x00").unwrap(),
            Format::Aedat4
        );
        assert_eq!(
            det("x.raw", b"Event Stream\x02\x00\x00\x01").unwrap(),
            Format::Es
        );
        assert_eq!(det("x.raw", b"\x93NUMPY\x01\x00").unwrap(), Format::Npy);
        assert_eq!(det("x.raw", b"t,x,y,p\n1,2,3,1\n").unwrap(), Format::Csv);
        assert_eq!(det("x.bin", b"12,3,4,1\n13,3,4,0\n").unwrap(), Format::Csv);
    }

    #[ebptv_macros::unit_test]
    fn dat_vs_raw() {
        let dat = b"% Data file containing CD events.\n% Version 2\n% Date 2017-10-31 11:29:21\n% Height 480\n% Width 640\n\x0c\x08";
        assert_eq!(det("x.raw", dat).unwrap(), Format::Dat);
        // No Version line, but the type/size bytes of DAT.
        assert_eq!(
            det("x.bin", b"% Date 2017-10-31 11:29:21\n\x00\x08").unwrap(),
            Format::Dat
        );
        // Old RAW headers also carry % Date.
        let raw = b"% Date 2020-09-25 07:48:29\n% evt 3.0\n% system_ID 48\n\x00\x08";
        assert_eq!(det("x.dat", raw).unwrap(), Format::Evt3);
    }

    #[ebptv_macros::unit_test]
    fn unknown_content() {
        let e = det("pic.raw", b"\x89PNG\r\n\x1a\n\x00\x00")
            .unwrap_err()
            .to_string();
        assert!(e.contains("PNG") && e.contains("pic.raw"), "{e}");
        let e = det("blob.xyz", b"\x01\x02\x03\x04")
            .unwrap_err()
            .to_string();
        assert!(e.contains("01 02 03 04") && e.contains("blob.xyz"), "{e}");
        let e = det("empty", b"").unwrap_err().to_string();
        assert!(e.contains("empty"), "{e}");
        // Headerless binary with a RAW extension: trust the extension.
        assert_eq!(det("x.raw", b"\x01\x02\x03\x04").unwrap(), Format::Evt3);
    }
}
