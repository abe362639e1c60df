include!("../engine/torch_link.rs");

fn main() {
    link_torch();
    embed_commit();
}

/// The commit this binary is built from, as `UDAPOSE_BUILD_COMMIT` (reports and manifests record
/// it, whatever directory the command later runs in); "unknown" outside a git checkout.
fn embed_commit() {
    let git = |args: &[&str]| -> Option<String> {
        let out = std::process::Command::new("git").args(args).current_dir(env!("CARGO_MANIFEST_DIR")).output().ok()?;
        out.status.success().then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
    };
    let commit = git(&["rev-parse", "--short", "HEAD"]).unwrap_or_else(|| "unknown".into());
    println!("cargo:rustc-env=UDAPOSE_BUILD_COMMIT={commit}");
    // A linked worktree keeps its HEAD in its own git dir and the branches in the common one.
    let dirs =
        [git(&["rev-parse", "--absolute-git-dir"]), git(&["rev-parse", "--path-format=absolute", "--git-common-dir"])];
    for dir in dirs.iter().flatten() {
        for path in ["HEAD", "refs/heads", "packed-refs"] {
            println!("cargo:rerun-if-changed={dir}/{path}");
        }
    }
}
