//! The NVIDIA Vulkan driver file (ICD) on headless hosts: why wgpu may see no NVIDIA GPU on a
//! machine that has one, and the exact fix.
//!
//! The NVIDIA driver installs an ICD file (`nvidia_icd.json`) naming `libGLX_nvidia.so.0`. On
//! headless and container GPU hosts (no X server, the driver mounted under `/usr/local/nvidia`)
//! that library fails `vkCreateInstance`, so the Vulkan loader offers no NVIDIA adapter. The same
//! driver's `libEGL_nvidia.so.0` carries the same Vulkan entry points and needs no display; an
//! ICD file naming it works. `scripts/vulkan-icd.sh` applies the same rule as
//! [`egl_icd_fix`] and `scripts/setup.sh --gpu` exports its choice.

use std::path::{Path, PathBuf};

/// Folders the Vulkan loader reads ICD files from, the container driver mount first.
const ICD_DIRS: &[&str] = &[
    "/usr/local/nvidia/share/vulkan/icd.d",
    "/etc/vulkan/icd.d",
    "/usr/share/vulkan/icd.d",
    "/usr/local/share/vulkan/icd.d",
];

/// Folders where the NVIDIA driver's libraries live, after the folder of the ICD's own library.
const LIB_DIRS: &[&str] = &[
    "/usr/local/nvidia/lib64",
    "/usr/local/nvidia/lib",
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib64",
    "/usr/lib",
    "/usr/lib/aarch64-linux-gnu/tegra",
];

/// What an NVIDIA host needs for headless Vulkan: the ICD file to write and where.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IcdFix {
    /// The driver's own ICD file (the one naming `libGLX_nvidia`).
    pub driver_icd: PathBuf,
    /// Absolute path of `libEGL_nvidia.so.0` as the host sees it (without the search root).
    pub egl_library: PathBuf,
    /// The ICD file's JSON text: `library_path` = [`Self::egl_library`], the driver file's
    /// `api_version`.
    pub json: String,
}

impl IcdFix {
    /// Shell commands that write the ICD file to `target` and point the Vulkan loader at it.
    pub fn commands(&self, target: &Path) -> String {
        format!(
            "printf '%s\\n' '{}' > {t}; export VK_DRIVER_FILES={t}",
            self.json,
            t = target.display()
        )
    }
}

/// The value of `"key": "value"` in an ICD file's JSON (`None` when absent or unreadable).
fn json_field(path: &Path, key: &str) -> Option<String> {
    let text = std::fs::read_to_string(path).ok()?;
    let value: serde_json::Value = serde_json::from_str(&text).ok()?;
    value.get("ICD")?.get(key)?.as_str().map(str::to_owned)
}

/// Whether an NVIDIA kernel driver is loaded on this machine (`/proc/driver/nvidia`).
pub fn nvidia_driver_present() -> bool {
    Path::new("/proc/driver/nvidia").exists()
}

/// The EGL ICD fix for the host whose file system is under `root` (`/` on a real host; a fake
/// tree in tests): `Some` when an NVIDIA ICD file names `libGLX_nvidia` (or any NVIDIA library
/// but `libEGL_nvidia`) and `libEGL_nvidia.so.0` exists beside that library or in a driver
/// folder; `None` when there is no NVIDIA ICD file, one already names `libEGL_nvidia`, or no
/// EGL library is found. Files are read in folder order, then by name, so the answer is the
/// same on every call.
pub fn egl_icd_fix(root: &Path) -> Option<IcdFix> {
    let under = |p: &str| root.join(p.trim_start_matches('/'));
    let mut driver: Option<(PathBuf, String)> = None;
    for dir in ICD_DIRS {
        let Ok(entries) = std::fs::read_dir(under(dir)) else {
            continue;
        };
        let mut files: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "json"))
            .collect();
        files.sort();
        for f in files {
            let Some(lib) = json_field(&f, "library_path") else {
                continue;
            };
            if lib.contains("EGL_nvidia") {
                return None;
            }
            if lib.contains("nvidia") && driver.is_none() {
                driver = Some((f, lib));
            }
        }
    }
    let (driver_icd, lib) = driver?;
    let api = json_field(&driver_icd, "api_version").unwrap_or_else(|| "1.3.0".into());
    let own_dir = Path::new(&lib)
        .is_absolute()
        .then(|| Path::new(&lib).parent().map(Path::to_path_buf))
        .flatten();
    let dirs = own_dir
        .into_iter()
        .chain(LIB_DIRS.iter().map(PathBuf::from));
    for d in dirs {
        let egl = d.join("libEGL_nvidia.so.0");
        if under(&egl.to_string_lossy()).exists() {
            let json = serde_json::json!({
                "file_format_version": "1.0.1",
                "ICD": {"library_path": egl.to_string_lossy(), "api_version": api}
            })
            .to_string();
            return Some(IcdFix {
                driver_icd,
                egl_library: egl,
                json,
            });
        }
    }
    None
}

/// Where the fix's ICD file goes: `$HOME/.cache/slag/nvidia_icd_egl.json` (the path
/// `scripts/vulkan-icd.sh` writes), or the temporary folder without `$HOME`.
pub fn fix_target() -> PathBuf {
    std::env::var_os("HOME")
        .map(|h| PathBuf::from(h).join(".cache/slag"))
        .unwrap_or_else(std::env::temp_dir)
        .join("nvidia_icd_egl.json")
}

/// The sentence for an error when Vulkan offers no GPU adapter (`found` names what it offers,
/// empty for none) on a host with an NVIDIA driver: the exact commands when the EGL fix applies,
/// else what to check. `None` when no NVIDIA driver is present (the plain "install a driver"
/// message then applies).
pub fn no_gpu_adapter_hint(found: &str, root: &Path, driver_present: bool) -> Option<String> {
    if !driver_present {
        return None;
    }
    let offered = if found.is_empty() {
        "no Vulkan adapter".to_string()
    } else {
        format!("only CPU Vulkan adapters ({found})")
    };
    Some(match egl_icd_fix(root) {
        Some(fix) => format!(
            "an NVIDIA driver is loaded but Vulkan offers {offered}: its ICD file {} names a \
             library that needs a display; run `{}` (or source `scripts/setup.sh --gpu`, which \
             does it) and start again",
            fix.driver_icd.display(),
            fix.commands(&fix_target())
        ),
        None => format!(
            "an NVIDIA driver is loaded but Vulkan offers {offered}: check that the driver's \
             Vulkan ICD file (nvidia_icd.json) is installed and VK_DRIVER_FILES, if set, names \
             it; to use a CPU adapter anyway, set SLAG_WGPU_ADAPTER to its name"
        ),
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn write(root: &Path, rel: &str, text: &str) {
        let p = root.join(rel);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, text).unwrap();
    }

    const GLX_ICD: &str = r#"{"file_format_version":"1.0.1","ICD":{"library_path":"libGLX_nvidia.so.0","api_version":"1.4.312"}}"#;

    #[test]
    fn a_container_host_gets_the_egl_library_of_the_driver_mount() {
        let t = tempfile::tempdir().unwrap();
        write(
            t.path(),
            "usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json",
            GLX_ICD,
        );
        write(t.path(), "usr/local/nvidia/lib64/libEGL_nvidia.so.0", "");
        write(
            t.path(),
            "usr/share/vulkan/icd.d/lvp_icd.x86_64.json",
            r#"{"file_format_version":"1.0.0","ICD":{"library_path":"/usr/lib/x86_64-linux-gnu/libvulkan_lvp.so","api_version":"1.3.255"}}"#,
        );
        let fix = egl_icd_fix(t.path()).expect("a fix");
        assert_eq!(
            fix.egl_library,
            Path::new("/usr/local/nvidia/lib64/libEGL_nvidia.so.0")
        );
        let v: serde_json::Value = serde_json::from_str(&fix.json).unwrap();
        assert_eq!(
            v["ICD"]["library_path"],
            "/usr/local/nvidia/lib64/libEGL_nvidia.so.0"
        );
        assert_eq!(v["ICD"]["api_version"], "1.4.312");
        let cmd = fix.commands(Path::new("/x/icd.json"));
        assert!(cmd.ends_with("export VK_DRIVER_FILES=/x/icd.json"), "{cmd}");
        let hint = no_gpu_adapter_hint("llvmpipe (Cpu)", t.path(), true).unwrap();
        assert!(
            hint.contains("only CPU Vulkan adapters (llvmpipe (Cpu))"),
            "{hint}"
        );
        assert!(hint.contains("libEGL_nvidia.so.0"), "{hint}");
    }

    #[test]
    fn the_library_beside_an_absolute_driver_library_wins() {
        let t = tempfile::tempdir().unwrap();
        write(
            t.path(),
            "etc/vulkan/icd.d/nvidia_icd.json",
            r#"{"ICD":{"library_path":"/opt/drv/libGLX_nvidia.so.0","api_version":"1.3.0"}}"#,
        );
        write(t.path(), "opt/drv/libEGL_nvidia.so.0", "");
        write(t.path(), "usr/lib64/libEGL_nvidia.so.0", "");
        let fix = egl_icd_fix(t.path()).unwrap();
        assert_eq!(fix.egl_library, Path::new("/opt/drv/libEGL_nvidia.so.0"));
    }

    #[test]
    fn no_fix_without_an_nvidia_icd_an_egl_icd_already_or_no_egl_library() {
        let t = tempfile::tempdir().unwrap();
        assert_eq!(egl_icd_fix(t.path()), None);
        assert_eq!(no_gpu_adapter_hint("", t.path(), false), None);
        write(t.path(), "usr/share/vulkan/icd.d/nvidia_icd.json", GLX_ICD);
        assert_eq!(egl_icd_fix(t.path()), None, "no libEGL_nvidia anywhere");
        let hint = no_gpu_adapter_hint("", t.path(), true).unwrap();
        assert!(
            hint.contains("no Vulkan adapter") && hint.contains("nvidia_icd.json"),
            "{hint}"
        );
        write(t.path(), "usr/lib64/libEGL_nvidia.so.0", "");
        assert!(egl_icd_fix(t.path()).is_some());
        write(
            t.path(),
            "etc/vulkan/icd.d/nvidia_egl.json",
            r#"{"ICD":{"library_path":"libEGL_nvidia.so.0","api_version":"1.3.0"}}"#,
        );
        assert_eq!(egl_icd_fix(t.path()), None, "an EGL ICD is there already");
    }

    /// `scripts/vulkan-icd.sh` applies the same rule as [`egl_icd_fix`] on the same fake host.
    #[test]
    fn the_setup_script_makes_the_same_choice() {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/vulkan-icd.sh");
        let t = tempfile::tempdir().unwrap();
        let run = |root: &Path| {
            let out = std::process::Command::new("bash")
                .arg(&script)
                .env("SLAG_ICD_ROOT", root)
                .env("SLAG_ICD_DIR", root.join("cache"))
                .env_remove("VK_DRIVER_FILES")
                .env_remove("VK_ICD_FILENAMES")
                .output()
                .unwrap();
            assert!(
                out.status.success(),
                "{}",
                String::from_utf8_lossy(&out.stderr)
            );
            String::from_utf8(out.stdout).unwrap().trim().to_string()
        };
        assert_eq!(run(t.path()), "", "no NVIDIA ICD: nothing to pick");
        write(
            t.path(),
            "usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json",
            GLX_ICD,
        );
        let own = t
            .path()
            .join("usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json");
        assert_eq!(
            run(t.path()),
            own.to_string_lossy(),
            "no EGL library: the driver's own"
        );
        write(t.path(), "usr/local/nvidia/lib64/libEGL_nvidia.so.0", "");
        let picked = run(t.path());
        assert_eq!(
            picked,
            t.path().join("cache/nvidia_icd_egl.json").to_string_lossy()
        );
        let got: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&picked).unwrap()).unwrap();
        let want: serde_json::Value =
            serde_json::from_str(&egl_icd_fix(t.path()).unwrap().json).unwrap();
        assert_eq!(got, want);
    }
}
