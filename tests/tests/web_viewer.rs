//! The web page in a real browser: encode snowmiku-mini (graph masks + color-clip) → partition
//! with `--display-ply` → shard server → `slag-edge fetch` → `slag-edge serve` (with the vendored
//! viewer) → headless Chromium (software WebGL, SwiftShader) types "pink" and "red" into the page
//! (`edge/web/e2e.mjs`, playwright-core) → the screenshots are checked here: the "pink" render
//! shows magenta (highlight) pixels, the "red" one (no match at the paper threshold) none.
//!
//! Needs Node.js, `bash scripts/web-vendor.sh` (viewer bundles + playwright-core) and Chromium
//! (`/usr/bin/chromium` or `$CHROMIUM`); `scripts/test.sh` sets all up and exports
//! `SLAG_WEB_E2E=1`, which turns a missing prerequisite into a failure. Without it the test
//! says what is missing and returns. `SLAG_WEB_E2E_OUT=DIR` keeps the screenshots.

#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::time::Duration;

use slag_tests::{robot_path, test_runtime};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// What is missing for the browser run, if anything.
fn missing_prerequisites(chromium: &Path) -> Vec<String> {
    let web = repo().join("edge/web");
    let mut miss = vec![];
    if std::process::Command::new("node")
        .arg("--version")
        .output()
        .is_err()
    {
        miss.push("node (apt-get install nodejs npm)".into());
    }
    for f in [
        "vendor/gaussian-splats-3d.module.js",
        "vendor/three.module.js",
        "node_modules/playwright-core/package.json",
    ] {
        if !web.join(f).exists() {
            miss.push(format!("edge/web/{f} (bash scripts/web-vendor.sh)"));
        }
    }
    if !chromium.exists() {
        miss.push(format!("{} (apt-get install chromium)", chromium.display()));
    }
    miss
}

/// Pixels the highlight paints: strongly magenta (red and blue high, green low). The page dims
/// every other Gaussian to 35 % of its colour, so the scene itself stays far from this.
/// Painted (highlight) pixels and lit pixels of a screenshot. The page paints each object's
/// matches in its palette colour and other matches magenta, at full brightness, and dims every
/// other Gaussian to 0.35 of its colour (`dim=0.35`): a pixel with a channel ≥ 140 is painted.
fn highlight_pixels(png: &Path) -> (usize, usize) {
    let img = image::open(png).unwrap().to_rgb8();
    // Skip the 44-px control bar at the top.
    let n = img
        .enumerate_pixels()
        .filter(|(_, y, _)| *y >= 50)
        .filter(|(_, _, p)| p.0.iter().any(|&c| c >= 140))
        .count();
    let lit = img
        .enumerate_pixels()
        .filter(|(_, y, _)| *y >= 50)
        .filter(|(_, _, p)| p.0.iter().any(|&c| c > 30))
        .count();
    (n, lit)
}

#[test]
fn page_renders_pink_matches_highlighted_in_headless_chromium() {
    let chromium = PathBuf::from(std::env::var("CHROMIUM").unwrap_or("/usr/bin/chromium".into()));
    let miss = missing_prerequisites(&chromium);
    if !miss.is_empty() {
        let msg = format!(
            "web viewer e2e needs: {}; `bash scripts/test.sh` installs them",
            miss.join(", ")
        );
        assert!(std::env::var("SLAG_WEB_E2E").is_err(), "{msg}");
        eprintln!("SKIPPED: {msg}");
        return;
    }
    let rt = test_runtime();
    let robot = robot_path(
        &rt,
        "f16",
        true,
        Duration::from_secs(120),
        Some(repo().join("edge/web")),
    );
    let edge_url = robot.edge_url.clone();
    // Ground truth from the JSON API: pink matches a region, red nothing.
    let count = |text: &str| {
        rt.block_on(async {
            let v: serde_json::Value = reqwest::get(format!("{edge_url}/query?text={text}"))
                .await
                .unwrap()
                .json()
                .await
                .unwrap();
            v["summary"]["count"].as_u64().unwrap()
        })
    };
    let (pink, red) = (count("pink"), count("red"));
    assert!(pink > 100 && red == 0, "pink {pink}, red {red}");

    let shots = std::env::var("SLAG_WEB_E2E_OUT")
        .map(PathBuf::from)
        .unwrap_or_else(|_| robot.dir.path().join("shots"));
    // The servers run on `rt`'s workers while node drives the browser.
    let node = std::process::Command::new("node")
        .arg(repo().join("edge/web/e2e.mjs"))
        .arg(&edge_url)
        .arg(&shots)
        .args(["pink", "red"])
        .env("CHROMIUM", &chromium)
        .output()
        .unwrap();
    let log =
        String::from_utf8_lossy(&node.stdout).to_string() + &String::from_utf8_lossy(&node.stderr);
    assert!(node.status.success(), "browser run failed:\n{log}");
    let result: serde_json::Value =
        serde_json::from_slice(&std::fs::read(shots.join("result.json")).unwrap()).unwrap();
    let r = result["results"].as_array().unwrap();
    assert_eq!(r[0]["matches"].as_u64(), Some(pink), "{log}");
    assert_eq!(r[1]["matches"].as_u64(), Some(0), "{log}");
    let (m_pink, lit_pink) = highlight_pixels(Path::new(r[0]["png"].as_str().unwrap()));
    let (m_red, lit_red) = highlight_pixels(Path::new(r[1]["png"].as_str().unwrap()));
    eprintln!(
        "pink: {m_pink} painted of {lit_pink} lit pixels; red: {m_red} painted of {lit_red} lit"
    );
    assert!(
        lit_pink > 2000 && lit_red > 2000,
        "the scene did not render:\n{log}"
    );
    assert!(
        m_pink > 200,
        "no highlight in the pink render ({m_pink} px):\n{log}"
    );
    assert!(
        m_red < 20,
        "highlight pixels without matches ({m_red} px):\n{log}"
    );
    drop(rt);
}
