//! Rebuilds slag-edge when the web page or the vendored viewer changes: the viewer bundles
//! (`edge/web/vendor`, made by `scripts/web-vendor.sh`) are embedded when present at build time
//! (`view::Vendored`), and a folder that appears after a first build must trigger a rebuild.

fn main() {
    for p in ["web/index.html", "web/app.js", "web/vendor"] {
        println!("cargo:rerun-if-changed={p}");
    }
}
