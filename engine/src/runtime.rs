//! What the linked libtorch offers on this machine, and thread-pool sizing.

use serde::Serialize;

/// Version of the libtorch the engine was built against (read from the wheel at build time).
pub const TORCH_VERSION: &str = env!("UDAPOSE_TORCH_VERSION");

#[derive(Clone, Debug, Serialize)]
pub struct RuntimeInfo {
    pub torch_version: &'static str,
    pub cuda_available: bool,
    pub cuda_devices: i64,
    pub cudnn_available: bool,
    pub torch_threads: i32,
    pub torch_interop_threads: i32,
    pub rayon_threads: usize,
    pub cpus: usize,
}

impl RuntimeInfo {
    pub fn detect() -> Self {
        RuntimeInfo {
            torch_version: TORCH_VERSION,
            cuda_available: tch::Cuda::is_available(),
            cuda_devices: tch::Cuda::device_count(),
            cudnn_available: tch::Cuda::cudnn_is_available(),
            torch_threads: tch::get_num_threads(),
            torch_interop_threads: tch::get_num_interop_threads(),
            rayon_threads: rayon::current_num_threads(),
            cpus: cores(),
        }
    }

    /// The device new tensors should go to: the first GPU when present.
    pub fn device(&self) -> tch::Device {
        if self.cuda_available { tch::Device::Cuda(0) } else { tch::Device::Cpu }
    }
}

/// The cores this process may use (the cgroup's quota and the affinity mask included), at least 1.
pub fn cores() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// The CPU's model name (from /proc/cpuinfo), for benchmark reports.
pub fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .map(|l| l.split(':').nth(1).unwrap_or("").trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into())
}
