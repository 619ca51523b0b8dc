//! PNG and GIF writing, and side-by-side layouts of frames.

use std::io::BufWriter;
use std::path::Path;

use image::codecs::gif::{GifEncoder, Repeat};
use image::codecs::png::PngEncoder;
use image::{Delay, DynamicImage, Frame, ImageEncoder, Rgb, RgbImage};

use crate::{Error, Image};

/// Colour of the gaps between panels of a layout (light grey).
pub const GAP_COLOR: [u8; 3] = [200, 200, 200];

/// Lays `rows` of pictures out on a grid with `gap_px` pixels of [`GAP_COLOR`] between
/// panels. Column `j` is as wide as its widest picture, row `i` as tall as its tallest; smaller
/// pictures sit at the top left of their cell; missing cells (short rows) stay gap-coloured.
///
/// # Errors
/// [`Error::ImageSize`] when there is no picture at all.
///
/// ```
/// use gsplat::{grid, Image};
/// let a = Image::blank(4, 3).to_rgb8();
/// let g = grid(&[vec![a.clone(), a.clone()], vec![a]], 2)?;
/// assert_eq!(g.dimensions(), (4 + 2 + 4, 3 + 2 + 3));
/// # Ok::<(), gsplat::Error>(())
/// ```
pub fn grid(rows: &[Vec<RgbImage>], gap_px: u32) -> Result<RgbImage, Error> {
    let cols = rows.iter().map(Vec::len).max().unwrap_or(0);
    if cols == 0 {
        return Err(Error::ImageSize("grid: no pictures".into()));
    }
    let mut col_w = vec![0u32; cols];
    let mut row_h = vec![0u32; rows.len()];
    for (i, row) in rows.iter().enumerate() {
        for (j, p) in row.iter().enumerate() {
            col_w[j] = col_w[j].max(p.width());
            row_h[i] = row_h[i].max(p.height());
        }
    }
    let gaps = |n: usize| gap_px * (n as u32).saturating_sub(1);
    let width = col_w.iter().sum::<u32>() + gaps(cols);
    let height = row_h.iter().sum::<u32>() + gaps(rows.len());
    let mut out = RgbImage::from_pixel(width, height, Rgb(GAP_COLOR));
    let mut y = 0;
    for (i, row) in rows.iter().enumerate() {
        let mut x = 0;
        for (j, p) in row.iter().enumerate() {
            for (px, py, v) in p.enumerate_pixels() {
                out.put_pixel(x + px, y + py, *v);
            }
            x += col_w[j] + gap_px;
        }
        y += row_h[i] + gap_px;
    }
    Ok(out)
}

/// Two renders next to each other (e.g. predicted | ground truth) with a `gap_px` gap.
pub fn side_by_side(left: &Image, right: &Image, gap_px: u32) -> RgbImage {
    // A grid of two non-empty pictures cannot fail; fall back to the left one regardless.
    let (l, r) = (left.to_rgb8(), right.to_rgb8());
    grid(&[vec![l.clone(), r]], gap_px).unwrap_or(l)
}

/// Writes an 8-bit RGB PNG, atomically (a temporary file renamed into place; missing parent
/// directories are created).
///
/// # Errors
/// [`Error::Io`] or [`Error::Encode`].
pub fn write_png(path: impl AsRef<Path>, picture: &RgbImage) -> Result<(), Error> {
    let path = path.as_ref();
    write_atomically(path, |w| {
        PngEncoder::new(w)
            .write_image(
                picture.as_raw(),
                picture.width(),
                picture.height(),
                image::ExtendedColorType::Rgb8,
            )
            .map_err(|source| Error::Encode {
                path: path.to_path_buf(),
                cause: source,
            })
    })
}

/// Writes an animated GIF that loops forever, showing each frame for `frame_ms` milliseconds.
/// Colours are quantised to GIF's 256-colour palettes by the `image` crate (deterministic).
/// Written atomically, as [`write_png`].
///
/// # Errors
/// [`Error::ImageSize`] for no frames or frames of different sizes, [`Error::Io`] or
/// [`Error::Encode`].
pub fn write_gif(path: impl AsRef<Path>, frames: &[RgbImage], frame_ms: u32) -> Result<(), Error> {
    let path = path.as_ref();
    let Some(first) = frames.first() else {
        return Err(Error::ImageSize("gif: no frames".into()));
    };
    if let Some(f) = frames.iter().find(|f| f.dimensions() != first.dimensions()) {
        return Err(Error::ImageSize(format!(
            "gif: frames of different sizes {:?} and {:?}",
            first.dimensions(),
            f.dimensions()
        )));
    }
    let encode_err = |source| Error::Encode {
        path: path.to_path_buf(),
        cause: source,
    };
    write_atomically(path, |w| {
        let mut enc = GifEncoder::new_with_speed(w, 10);
        enc.set_repeat(Repeat::Infinite).map_err(encode_err)?;
        let delay = Delay::from_numer_denom_ms(frame_ms, 1);
        for f in frames {
            let rgba = DynamicImage::ImageRgb8(f.clone()).into_rgba8();
            enc.encode_frame(Frame::from_parts(rgba, 0, 0, delay))
                .map_err(encode_err)?;
        }
        Ok(())
    })
}

/// Writes `path` through `write` atomically: into a temporary file beside it (creating missing
/// parent directories), flushed to disk and renamed over `path`, so a reader never sees a
/// half-written picture and a failed or interrupted write leaves the previous file intact.
/// (`dataset::write_atomic` does the same for bytes; the renderer stays free of the data crate
/// and streams its encoders into the file instead.)
pub(crate) fn write_atomically(
    path: &Path,
    write: impl FnOnce(&mut BufWriter<std::fs::File>) -> Result<(), Error>,
) -> Result<(), Error> {
    let io = |source| Error::Io {
        path: path.to_path_buf(),
        cause: source,
    };
    let Some(name) = path.file_name() else {
        return Err(io(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "not a file path",
        )));
    };
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(io)?;
    }
    let mut tmp_name = std::ffi::OsString::from(".");
    tmp_name.push(name);
    tmp_name.push(format!(".{}.tmp", std::process::id()));
    let tmp = path.with_file_name(tmp_name);
    let result = (|| {
        let mut w = BufWriter::new(std::fs::File::create(&tmp).map_err(io)?);
        write(&mut w)?;
        let file = w.into_inner().map_err(|e| io(e.into_error()))?;
        file.sync_all().map_err(io)?;
        std::fs::rename(&tmp, path).map_err(io)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

#[cfg(test)]
mod tests {
    use std::io::Write;

    use super::*;

    /// A write that fails half-way leaves the previous file as it was and no temporary file.
    #[test]
    fn a_failed_write_keeps_the_previous_file() {
        let dir = std::env::temp_dir().join(format!("gsplat-atomic-{}", std::process::id()));
        std::fs::remove_dir_all(&dir).ok();
        let path = dir.join("picture.png");
        write_atomically(&path, |w| {
            w.write_all(b"old").map_err(|e| Error::Io {
                path: path.clone(),
                cause: e,
            })
        })
        .unwrap();
        let failed = write_atomically(&path, |w| {
            w.write_all(b"half a new pict").unwrap();
            Err(Error::ImageSize("stopped on purpose".into()))
        });
        assert!(matches!(failed, Err(Error::ImageSize(_))));
        assert_eq!(std::fs::read(&path).unwrap(), b"old");
        assert_eq!(
            std::fs::read_dir(&dir).unwrap().count(),
            1,
            "a temporary file was left"
        );
        std::fs::remove_dir_all(&dir).ok();
    }
}
