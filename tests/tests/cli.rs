//! The `udapose` CLI against a real server: `estimate` on files, a folder and stdin, as a table
//! and as JSON (the HTTP API's fields), and `models`. Needs `make test`'s quick model and data.

mod support;

use std::{
    io::Write,
    process::{Command, Output, Stdio},
};

use support::{Server, beside_tests, quick_images};

fn udapose(server: &Server, args: &[&str], stdin: Option<&[u8]>) -> Output {
    let mut child = Command::new(beside_tests("udapose"))
        .arg("--endpoint")
        .arg(server.grpc_addr.to_string())
        .args(args)
        .env_remove("UDAPOSE_TOKEN")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the udapose binary (build the workspace first)");
    let mut input = child.stdin.take().unwrap();
    input.write_all(stdin.unwrap_or_default()).unwrap();
    drop(input);
    child.wait_with_output().unwrap()
}

#[test]
fn estimate_prints_poses_for_files_folders_and_stdin() {
    let server = Server::config("cli").quick_model().start();
    let images = quick_images("source", 2);
    let expected = server.request("POST", "/v1/pose/car", &[], &images[0].bytes).json();
    let azimuth = expected["estimates"][0]["azimuth_deg"].as_f64().unwrap();

    let file = images[0].path.display().to_string();
    let out = udapose(&server, &["estimate", "--category", "car", &file], None);
    let table = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(table.starts_with("IMAGE"), "{table}");
    assert!(table.contains(&format!("{azimuth:.1}°")) && table.contains("seed-"), "{table}");

    let out = udapose(&server, &["estimate", "--json", "-"], Some(&images[0].bytes));
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(json["estimates"], expected["estimates"], "stdin JSON equals the HTTP answer");

    // A folder: one JSON line per image, the 60 quick test images in name order.
    let folder = images[0].path.parent().unwrap().display().to_string();
    let out = udapose(&server, &["estimate", "--json", &folder], None);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let lines: Vec<serde_json::Value> =
        String::from_utf8_lossy(&out.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(lines.len(), 60);
    assert!(lines[0]["image"].as_str().unwrap().ends_with("00000.png"));

    let out = udapose(&server, &["estimate", "--category", "bus", &file], None);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("NotFound: unknown category"));

    let out = udapose(&server, &["models"], None);
    let table = String::from_utf8_lossy(&out.stdout);
    assert!(table.contains("car") && table.contains("yes"), "{table}");
}
