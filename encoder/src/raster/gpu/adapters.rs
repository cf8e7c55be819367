//! The Vulkan adapter the rasterizer runs on: the adapters ranked best first, or the one
//! `$SLAG_WGPU_ADAPTER` names (a substring of its name, or `#N` for the N-th of the ranked list).

use std::path::Path;

use slag_common::{Error, Result};

use super::{ADAPTER_ENV, icd};

/// The Vulkan adapters slag would use, best first: those matching `$SLAG_WGPU_ADAPTER`
/// (case-insensitive substring) if set, else ranked discrete, integrated, virtual, other, CPU
/// (Mesa lavapipe), in enumeration order within a rank.
///
/// Errors: [`Error::Gpu`] when there is no Vulkan adapter (install a driver), when an NVIDIA
/// driver is loaded but Vulkan offers only CPU adapters or none (the message gives the exact fix,
/// see [`icd`]; naming a CPU adapter in `$SLAG_WGPU_ADAPTER` runs on it anyway), or when none
/// matches `$SLAG_WGPU_ADAPTER` (the message lists what exists).
pub(super) fn ranked_adapters(instance: &wgpu::Instance) -> Result<Vec<wgpu::Adapter>> {
    let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::VULKAN));
    let names: Vec<String> = adapters.iter().map(label).collect();
    let wanted = std::env::var(ADAPTER_ENV).ok();
    // An NVIDIA host whose Vulkan offers no GPU: name the exact fix instead of running on
    // Mesa's CPU driver a hundred times slower (unless the CPU adapter was asked for by name).
    let only_cpu = adapters
        .iter()
        .all(|a| a.get_info().device_type == wgpu::DeviceType::Cpu);
    if only_cpu
        && wanted.is_none()
        && let Some(hint) = icd::no_gpu_adapter_hint(
            &names.join(", "),
            Path::new("/"),
            icd::nvidia_driver_present(),
        )
    {
        return Err(Error::Gpu(hint));
    }
    if adapters.is_empty() {
        return Err(Error::Gpu(
            "no Vulkan adapter found; install a Vulkan driver (on Debian/Ubuntu without a GPU: \
             `apt-get install mesa-vulkan-drivers` for the lavapipe CPU driver)"
                .into(),
        ));
    }
    if let Some(index) = wanted.as_deref().and_then(|w| w.strip_prefix('#')) {
        return adapter_at(rank_adapters(adapters), index);
    }
    if let Some(want) = wanted {
        let want_l = want.to_lowercase();
        let matching: Vec<wgpu::Adapter> = adapters
            .into_iter()
            .filter(|a| a.get_info().name.to_lowercase().contains(&want_l))
            .collect();
        if matching.is_empty() {
            return Err(Error::Gpu(format!(
                "{ADAPTER_ENV}={want:?} matches no Vulkan adapter; available: {}",
                names.join(", ")
            )));
        }
        return Ok(matching);
    }
    Ok(rank_adapters(adapters))
}

/// An adapter's name and type, as messages and the report show it.
fn label(adapter: &wgpu::Adapter) -> String {
    let info = adapter.get_info();
    format!("{} ({:?})", info.name, info.device_type)
}

/// `adapters` ranked discrete, integrated, virtual, other, CPU; enumeration order within a rank.
fn rank_adapters(mut adapters: Vec<wgpu::Adapter>) -> Vec<wgpu::Adapter> {
    use wgpu::DeviceType as D;
    let rank = |t: D| match t {
        D::DiscreteGpu => 0,
        D::IntegratedGpu => 1,
        D::VirtualGpu => 2,
        D::Other => 3,
        D::Cpu => 4,
    };
    adapters.sort_by_key(|a| rank(a.get_info().device_type));
    adapters
}

/// The adapter `#index` of `ranked` alone (`$SLAG_WGPU_ADAPTER=#N`).
///
/// Errors: [`Error::Gpu`] when `index` is not a number or past the list (naming what exists, in
/// its order).
fn adapter_at(ranked: Vec<wgpu::Adapter>, index: &str) -> Result<Vec<wgpu::Adapter>> {
    let n = ranked.len();
    let names: Vec<String> = ranked.iter().map(label).collect();
    match index.trim().parse::<usize>() {
        Ok(i) if i < n => Ok(ranked.into_iter().skip(i).take(1).collect()),
        _ => Err(Error::Gpu(format!(
            "{ADAPTER_ENV}=#{index}: give #0 to #{} (the adapters, best first, in the order \
             `--gpus` takes them: {}) or a substring of one's name",
            n.saturating_sub(1),
            names.join(", ")
        ))),
    }
}

/// Names and types of the adapters [`GpuRasterizer::new_many`] chooses from, best first.
///
/// Errors: as [`GpuRasterizer::new`] when no adapter exists.
pub fn adapter_names() -> Result<Vec<String>> {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::VULKAN;
    let instance = wgpu::Instance::new(desc);
    Ok(ranked_adapters(&instance)?.iter().map(label).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vulkan_adapters() -> Vec<wgpu::Adapter> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = wgpu::Backends::VULKAN;
        let instance = wgpu::Instance::new(desc);
        pollster::block_on(instance.enumerate_adapters(wgpu::Backends::VULKAN))
    }

    /// `#N` takes the N-th adapter of the ranked list alone; a number past the list or not a
    /// number is refused with the range and the adapters' names.
    #[test]
    fn an_index_picks_one_adapter_of_the_ranked_list() {
        let adapters = vulkan_adapters();
        if adapters.is_empty() {
            assert!(
                crate::raster::testdata::skip_gpu(),
                "no Vulkan adapter (lavapipe in CI)"
            );
            return;
        }
        let n = adapters.len();
        let names: Vec<String> = rank_adapters(vulkan_adapters()).iter().map(label).collect();
        for i in 0..n {
            let one = adapter_at(rank_adapters(vulkan_adapters()), &i.to_string()).unwrap();
            assert_eq!(one.len(), 1);
            assert_eq!(label(&one[0]), names[i]);
        }
        for bad in [n.to_string(), "x".to_string(), "-1".to_string()] {
            let e = adapter_at(rank_adapters(vulkan_adapters()), &bad).unwrap_err();
            let msg = e.to_string();
            assert!(
                msg.contains(&format!("#{}", n - 1)) && msg.contains(&names[0]),
                "{msg}"
            );
        }
    }
}
