//! TLS on both listeners: a CA made with `openssl`, a server certificate for 127.0.0.1 signed
//! by it; the client trusting the CA estimates over gRPC, curl over HTTPS; cleartext and
//! untrusted clients are refused. Needs `make test`'s quick model and data.

mod support;

use std::{path::Path, process::Command};

use support::{Server, quick_images, scratch_dir};
use udapose_client::{Client, ClientOptions};

fn openssl(args: &[&str], dir: &Path) {
    let out = Command::new("openssl").args(args).current_dir(dir).output().expect("running openssl");
    assert!(out.status.success(), "openssl {args:?}: {}", String::from_utf8_lossy(&out.stderr));
}

/// ca.pem, and server.pem / server.key for 127.0.0.1 signed by it.
fn certificates(dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    let ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"];
    openssl(
        &[
            &["req", "-x509"],
            &ec[..],
            &["-keyout", "ca.key", "-out", "ca.pem", "-days", "2", "-subj", "/CN=udapose test CA"],
        ]
        .concat(),
        dir,
    );
    openssl(
        &[&["req", "-new"], &ec[..], &["-keyout", "server.key", "-out", "server.csr", "-subj", "/CN=127.0.0.1"]]
            .concat(),
        dir,
    );
    std::fs::write(dir.join("ext.cnf"), "subjectAltName=IP:127.0.0.1,DNS:localhost\n").unwrap();
    let sign = ["x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial"];
    openssl(&[&sign[..], &["-out", "server.pem", "-days", "2", "-extfile", "ext.cnf"]].concat(), dir);
}

#[test]
fn tls_serves_trusting_clients_only() {
    let dir = scratch_dir("tls-certs");
    certificates(&dir);
    let server = Server::config("tls").quick_model().tls(&dir.join("server.pem"), &dir.join("server.key")).start();
    let image = quick_images("source", 1).remove(0);
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let endpoint = format!("https://{}", server.grpc_addr);

    let trusted = ClientOptions {
        ca_cert: Some(std::fs::read(dir.join("ca.pem")).unwrap()),
        ..ClientOptions::new(endpoint.clone())
    };
    let answer = runtime.block_on(async {
        let client = Client::connect_with(trusted).await.expect("connecting over TLS");
        client.estimate(udapose_client::request("car", image.bytes.clone())).await.expect("estimate over TLS")
    });
    assert_eq!(answer.estimates.len(), 1);

    // The system's roots do not know the test CA; cleartext gRPC cannot talk to a TLS port.
    let untrusted = runtime.block_on(Client::connect_with(ClientOptions::new(endpoint)));
    assert!(untrusted.is_err(), "connected without trusting the CA");
    let cleartext = runtime.block_on(async {
        let options = ClientOptions { retries: 0, ..ClientOptions::new(format!("http://{}", server.grpc_addr)) };
        match Client::connect_with(options).await {
            Ok(c) => c.list_models().await.map(|_| ()).map_err(|e| e.to_string()),
            Err(e) => Err(e.to_string()),
        }
    });
    assert!(cleartext.is_err(), "cleartext gRPC was served");

    // HTTPS: curl trusting the CA gets the same pose as gRPC.
    let out = Command::new("curl")
        .args(["-sS", "--cacert"])
        .arg(dir.join("ca.pem"))
        .args(["--data-binary", &format!("@{}", image.path.display())])
        .arg(format!("https://127.0.0.1:{}/v1/pose/car", server.http_addr.port()))
        .output()
        .expect("running curl");
    assert!(out.status.success(), "curl: {}", String::from_utf8_lossy(&out.stderr));
    let http: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(http["estimates"][0]["azimuth"].as_f64(), Some(answer.estimates[0].azimuth));
    // Cleartext HTTP to the TLS port gets no HTTP answer.
    assert!(support::http_request(server.http_addr, "GET", "/healthz", &[], b"").map_or(true, |r| r.status != 200));
    let _ = std::fs::remove_dir_all(&dir);
}
