// Shared by the build.rs of every package that links tch (included, not a crate, because
// `rustc-link-arg` applies per package). It makes binaries, tests and benches find libtorch
// without LD_LIBRARY_PATH (rpath) and keeps libtorch.so -- and with it libtorch_cuda -- in the
// dependency list (`--no-as-needed`), without which CUDA is silently unavailable.
// UDAPOSE_CUDA=0 skips the latter for CPU-only images that ship no CUDA libraries.
fn link_torch() {
    println!("cargo:rerun-if-env-changed=UDAPOSE_CUDA");
    println!("cargo:rerun-if-env-changed=DEP_TCH_LIBTORCH_LIB");
    let Ok(lib) = std::env::var("DEP_TCH_LIBTORCH_LIB") else {
        println!("cargo:warning=DEP_TCH_LIBTORCH_LIB unset: libtorch rpath not added");
        return;
    };
    println!("cargo:rustc-link-arg=-Wl,-rpath,{lib}");
    if std::env::var("UDAPOSE_CUDA").as_deref() != Ok("0") {
        println!("cargo:rustc-link-arg=-Wl,--no-as-needed");
        println!("cargo:rustc-link-arg=-ltorch");
        println!("cargo:rustc-link-arg=-Wl,--as-needed");
    }
    // The version of the libtorch we link, for `udapose-lab doctor` (torch's wheel layout:
    // torch/lib/libtorch.so next to torch/version.py).
    let version_py = std::path::Path::new(&lib).join("../version.py");
    println!("cargo:rerun-if-changed={}", version_py.display());
    let version = std::fs::read_to_string(&version_py)
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("__version__ = ").map(|v| v.trim_matches(['\'', '"']).to_string()))
        })
        .unwrap_or_else(|| "unknown".into());
    println!("cargo:rustc-env=UDAPOSE_TORCH_VERSION={version}");
}
