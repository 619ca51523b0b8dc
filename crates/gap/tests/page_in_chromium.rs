//! The report page drawn by a real browser: Debian's headless `chromium` renders a stored
//! bench report's page, and every chart shows up in the screenshot in its own colour.
//!
//! Needs `chromium` on the PATH (or `PGRD_CHROMIUM=<binary>`), so it is ignored by default:
//! `cargo test -p pgrd-gap --test page_in_chromium -- --ignored`.

use std::path::{Path, PathBuf};
use std::process::Command;

fn chromium() -> PathBuf {
    std::env::var_os("PGRD_CHROMIUM").map_or_else(|| PathBuf::from("chromium"), PathBuf::from)
}

/// Runs headless Chromium on `page` with `extra` arguments; the flags keep it off the network
/// (this machine has none) and out of the user's profile.
fn run_chromium(page: &Path, profile: &Path, extra: &[&str]) -> std::process::Output {
    let out = Command::new(chromium())
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .args(extra)
        .arg(format!("file://{}", page.display()))
        .output()
        .expect("chromium runs (install Debian's `chromium` or set PGRD_CHROMIUM)");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Pixels within a small distance of `rgb` (anti-aliased strokes blend at their edges).
fn pixels_near(img: &image::RgbImage, rgb: [u8; 3]) -> usize {
    img.pixels()
        .filter(|p| {
            p.0.iter()
                .zip(rgb)
                .all(|(a, b)| i32::from(*a).abs_diff(i32::from(b)) <= 12)
        })
        .count()
}

#[test]
#[ignore = "needs headless chromium"]
fn the_page_renders_with_every_chart_in_chromium() {
    let data = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data");
    // The paper's magnet ×4: `unknown` through the probe, with a before/after section.
    let text = std::fs::read_to_string(format!("{data}/paper-magnet-x4-seed0.json")).unwrap();
    let d: gap::Diagnosis = serde_json::from_str(&text).unwrap();
    let dir = std::env::temp_dir().join(format!("pgrd-page-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let page = dir.join("report.html");
    std::fs::write(&page, gap::render_html(&d, "paper magnet x4")).unwrap();
    let profile = dir.join("profile");

    // The parsed document: the verdict, and the four charts (heat map with its colour bar,
    // before/after curves, ranking, error over time).
    let dom = run_chromium(&page, &profile, &["--dump-dom"]);
    let dom = String::from_utf8_lossy(&dom.stdout);
    assert!(
        dom.contains("Verdict: <b>unknown</b>"),
        "{}",
        &dom[..dom.len().min(400)]
    );
    assert!(
        dom.matches("<svg").count() >= 4,
        "{} charts",
        dom.matches("<svg").count()
    );

    // The picture: each chart's colour is on the screen, so the SVG was drawn, not only parsed.
    let shot = dir.join("page.png");
    run_chromium(
        &page,
        &profile,
        &[
            "--window-size=1000,4000",
            &format!("--screenshot={}", shot.display()),
        ],
    );
    let img = image::open(&shot).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (1000, 4000));
    for (what, rgb) in [
        ("before curve", [0xc0, 0x39, 0x2b]),
        ("after curve", [0x1b, 0x7f, 0x3b]),
        ("error-over-time curve", [0x2c, 0x3e, 0x50]),
        ("heat map's low end", [40, 90, 200]),
        ("heat map's high end", [255, 50, 30]),
        ("chart background", [0xfa, 0xfa, 0xfa]),
    ] {
        let n = pixels_near(&img, rgb);
        assert!(n > 100, "{what}: {n} pixels of {rgb:?}");
    }
    std::fs::remove_dir_all(&dir).ok();
}
