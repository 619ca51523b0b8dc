//! `.ply` reading and writing; PNG and GIF output.

// Index loops over parallel arrays read more plainly here than zipped iterators.
#![allow(clippy::needless_range_loop)]

use std::path::{Path, PathBuf};

use glam::{Quat, Vec3};
use gsplat::{
    Error, Gaussians, Image, grid, parse_ply, read_ply, side_by_side, write_gif, write_ply,
    write_png,
};

/// A file path in a directory of its own under the system temp dir; the directory is removed
/// when this is dropped (kept when the test panics, for a look).
struct TempFile {
    dir: PathBuf,
    path: PathBuf,
}

impl std::ops::Deref for TempFile {
    type Target = std::path::Path;
    fn deref(&self) -> &std::path::Path {
        &self.path
    }
}

impl AsRef<std::path::Path> for TempFile {
    fn as_ref(&self) -> &std::path::Path {
        &self.path
    }
}

impl Drop for TempFile {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

fn temp(name: &str) -> TempFile {
    let dir = std::env::temp_dir().join(format!("pgrd-gsplat-test-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    TempFile {
        path: dir.join(name),
        dir,
    }
}

const C0: f64 = 0.282_094_791_773_878_14; // 1 / (2 sqrt(pi))

/// A 3DGS header with extra properties around the ones we read (normals first, f_rest after,
/// as the 3DGS trainer writes them).
fn header(n: usize, format: &str) -> String {
    let mut h = format!("ply\nformat {format} 1.0\ncomment written by hand\nelement vertex {n}\n");
    for p in [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "f_rest_0", "opacity",
    ] {
        h.push_str(&format!("property float {p}\n"));
    }
    for p in [
        "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
    ] {
        h.push_str(&format!("property float {p}\n"));
    }
    h.push_str("end_header\n");
    h
}

/// Two Gaussians' raw 3DGS values in header order.
fn rows() -> [[f32; 18]; 2] {
    [
        [
            0.1, 0.2, 0.3, 0.0, 0.0, 1.0, 0.0, 1.0, -1.0, 9.0, 0.0, -3.0, -4.0, -5.0, 1.0, 0.0,
            0.0, 0.0,
        ],
        [
            -1.0, 2.0, 5.0, 0.0, 0.0, 1.0, -3.0, 0.5, 2.0, 9.0, 2.0, 0.0, -1.0, -2.0, 0.0, 0.0,
            0.0, 2.0,
        ],
    ]
}

fn check_decoded(g: &Gaussians) {
    assert_eq!(g.len(), 2);
    let close = |a: f32, b: f64| (a as f64 - b).abs() < 1e-6;
    assert_eq!(g.means[0], Vec3::new(0.1, 0.2, 0.3));
    // Colour: 0.5 + C0 f_dc, clamped at 0.
    assert!(
        close(g.colors[0][0], 0.5)
            && close(g.colors[0][1], 0.5 + C0)
            && close(g.colors[0][2], 0.5 - C0)
    );
    assert!(close(g.colors[1][0], 0.0), "0.5 - 3 C0 < 0 is clamped");
    assert!(close(g.colors[1][2], 0.5 + 2.0 * C0));
    // Opacity: sigmoid of the logit.
    assert!(close(g.opacities[0], 0.5) && close(g.opacities[1], 1.0 / (1.0 + (-2f64).exp())));
    // Scales: exp of the logs.
    assert!(close(g.scales[0].x, (-3f64).exp()) && close(g.scales[0].z, (-5f64).exp()));
    assert!(close(g.scales[1].x, 1.0));
    // Quaternion stored w, x, y, z: the second is (w, x, y, z) = (0, 0, 0, 2), a 180° turn about z.
    assert_eq!(g.rotations[0], Quat::IDENTITY);
    assert_eq!(g.rotations[1], Quat::from_xyzw(0.0, 0.0, 2.0, 0.0));
}

#[test]
fn reads_binary_little_endian_3dgs_ply() {
    let mut bytes = header(2, "binary_little_endian").into_bytes();
    for row in rows() {
        for v in row {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    let path = temp("two.ply");
    std::fs::write(&path, &bytes).unwrap();
    check_decoded(&read_ply(&path).unwrap());
    std::fs::remove_file(&path).ok();
    // Big-endian and ASCII variants of the same data.
    let mut big = header(2, "binary_big_endian").into_bytes();
    for row in rows() {
        for v in row {
            big.extend_from_slice(&v.to_be_bytes());
        }
    }
    check_decoded(&parse_ply(&big, Path::new("big.ply")).unwrap());
    let mut ascii = header(2, "ascii");
    for row in rows() {
        ascii.push_str(&row.map(|v| v.to_string()).join(" "));
        ascii.push('\n');
    }
    check_decoded(&parse_ply(ascii.as_bytes(), Path::new("ascii.ply")).unwrap());
}

#[test]
fn malformed_ply_is_an_error() {
    let mut good = header(2, "binary_little_endian").into_bytes();
    for row in rows() {
        for v in row {
            good.extend_from_slice(&v.to_le_bytes());
        }
    }
    let p = Path::new("x.ply");
    let is_ply_err = |b: &[u8]| matches!(parse_ply(b, p), Err(Error::Ply { .. }));
    assert!(is_ply_err(&good[..good.len() - 3]), "truncated");
    assert!(
        is_ply_err(b"ply\nformat binary_little_endian 1.0\n"),
        "no end_header"
    );
    assert!(is_ply_err(b"nope\nend_header\n"), "no magic");
    assert!(is_ply_err(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n\0\0\0\0"));
    let huge = String::from_utf8_lossy(&good)
        .replace("element vertex 2", "element vertex 18446744073709551615");
    assert!(is_ply_err(huge.as_bytes()), "lying vertex count");
    let mut nan = good.clone();
    let at = good.len() - 18 * 4; // x of the second Gaussian
    nan[at..at + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    assert!(is_ply_err(&nan), "NaN mean");
    assert!(matches!(
        read_ply("/nonexistent/dir/x.ply"),
        Err(Error::Io { .. })
    ));
}

#[test]
fn write_then_read_round_trips() {
    let g = Gaussians::new(
        vec![Vec3::new(0.1, -0.2, 0.3), Vec3::new(1.0, 2.0, 3.0)],
        vec![
            Quat::from_rotation_x(0.7),
            Quat::from_xyzw(0.1, 0.2, 0.3, 0.4),
        ],
        vec![Vec3::new(0.01, 0.02, 0.03), Vec3::new(0.5, 0.001, 0.2)],
        vec![0.3, 0.99],
        vec![[0.2, 0.4, 0.6], [1.0, 0.0, 0.5]],
    )
    .unwrap();
    let path = temp("round.ply");
    write_ply(&path, &g).unwrap();
    let back = read_ply(&path).unwrap();
    std::fs::remove_file(&path).ok();
    for i in 0..2 {
        assert!((back.means[i] - g.means[i]).length() < 1e-7);
        assert!(back.rotations[i].abs_diff_eq(g.rotations[i], 1e-7));
        assert!(
            (back.scales[i] - g.scales[i]).abs().max_element() < 1e-6 * g.scales[i].max_element()
        );
        assert!((back.opacities[i] - g.opacities[i]).abs() < 1e-6);
        for c in 0..3 {
            assert!((back.colors[i][c] - g.colors[i][c]).abs() < 1e-6);
        }
    }
}

fn gradient(w: usize, h: usize) -> Image {
    let mut img = Image::blank(w, h);
    for y in 0..h {
        for x in 0..w {
            let k = img.index(x, y);
            img.rgb[3 * k] = x as f32 / (w - 1) as f32;
            img.rgb[3 * k + 1] = y as f32 / (h - 1) as f32;
            img.rgb[3 * k + 2] = 2.0; // clamped to 255
            img.alpha[k] = if x < w / 2 { 0.5 } else { 0.05 };
        }
    }
    img
}

#[test]
fn png_round_trips_and_layouts_place_panels() {
    let (a, b) = (gradient(10, 6), gradient(7, 9));
    let pair = side_by_side(&a, &b, 3);
    assert_eq!(pair.dimensions(), (10 + 3 + 7, 9));
    assert_eq!(pair.get_pixel(9, 0).0, [255, 0, 255]);
    assert_eq!(pair.get_pixel(10, 0).0, gsplat::GAP_COLOR);
    assert_eq!(pair.get_pixel(13, 8).0, [0, 255, 255]);
    assert_eq!(
        pair.get_pixel(5, 7).0,
        gsplat::GAP_COLOR,
        "below the shorter panel"
    );
    let path = temp("pair.png");
    write_png(&path, &pair).unwrap();
    let back = image::open(&path).unwrap().into_rgb8();
    assert_eq!(back, pair);
    std::fs::remove_file(&path).ok();
    assert!(grid(&[], 2).is_err());
    // Missing directories are created; a directory that cannot be (its parent is a file) is
    // an I/O error, not a panic.
    let nested = temp("nested").join("a").join("pair.png");
    write_png(&nested, &pair).unwrap();
    assert_eq!(image::open(&nested).unwrap().into_rgb8(), pair);
    let names: Vec<_> = std::fs::read_dir(nested.parent().unwrap())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(
        names,
        vec![std::ffi::OsString::from("pair.png")],
        "no temporary file left"
    );
    std::fs::remove_dir_all(temp("nested")).ok();
    let blocker = temp("blocker");
    std::fs::write(&blocker, b"a file").unwrap();
    assert!(matches!(
        write_png(blocker.join("x.png"), &pair),
        Err(Error::Io { .. })
    ));
    std::fs::remove_file(&blocker).ok();
    // Masks: alpha strictly above the threshold.
    let mask = a.mask(gsplat::MASK_THRESHOLD);
    assert_eq!(mask.iter().filter(|m| **m).count(), 5 * 6);
    assert_eq!(a.mask_rgb8(0.1).get_pixel(0, 0).0, [0, 0, 0]);
}

#[test]
fn gif_has_every_frame() {
    let frames: Vec<_> = (0..4).map(|_| gradient(12, 8).to_rgb8()).collect();
    let path = temp("anim.gif");
    write_gif(&path, &frames, 250).unwrap();
    let file = std::io::BufReader::new(std::fs::File::open(&path).unwrap());
    let decoder = image::codecs::gif::GifDecoder::new(file).unwrap();
    let decoded = image::AnimationDecoder::into_frames(decoder)
        .collect_frames()
        .unwrap();
    assert_eq!(decoded.len(), 4);
    assert_eq!(decoded[0].buffer().dimensions(), (12, 8));
    assert_eq!(decoded[1].delay().numer_denom_ms(), (250, 1));
    std::fs::remove_file(&path).ok();
    assert!(write_gif(&path, &[], 100).is_err());
    let odd = vec![frames[0].clone(), gradient(5, 5).to_rgb8()];
    assert!(matches!(
        write_gif(&path, &odd, 100),
        Err(Error::ImageSize(_))
    ));
}
