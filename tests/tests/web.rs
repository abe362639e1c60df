//! The web page at `/`, driven by a headless Chromium over WebDriver (Debian's `chromium` and
//! `chromium-driver`; `make test` installs them): a person uploads an image and sees the angles
//! and the cuboid drawn over it. Needs `make test`'s quick model and data.

mod support;

use std::{
    process::{Child, Command, Stdio},
    thread,
    time::{Duration, Instant},
};

use serde_json::{Value, json};
use support::{Server, free_addrs, http_request, quick_images};

/// W3C WebDriver's key for an element reference.
const ELEMENT: &str = "element-6066-11e4-a52e-4f735466cecf";

struct Driver {
    child: Child,
    addr: std::net::SocketAddr,
    session: String,
}

impl Driver {
    fn start() -> Driver {
        let chromium =
            ["/usr/bin/chromium", "/usr/bin/chromium-browser"].into_iter().find(|p| std::path::Path::new(p).exists());
        let chromium =
            chromium.expect("chromium not installed: `make test` installs Debian's chromium and chromium-driver");
        let [addr] = free_addrs();
        let child = Command::new("chromedriver")
            .arg(format!("--port={}", addr.port()))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("chromedriver not found: `make test` installs Debian's chromium-driver");
        let mut driver = Driver { child, addr, session: String::new() };
        let deadline = Instant::now() + Duration::from_secs(20);
        while !driver.call("GET", "/status", None).is_ok_and(|v| v["value"]["ready"] == true) {
            assert!(Instant::now() < deadline, "chromedriver did not start");
            thread::sleep(Duration::from_millis(100));
        }
        let caps = json!({ "capabilities": { "alwaysMatch": { "browserName": "chrome", "goog:chromeOptions": {
            "binary": chromium,
            "args": ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1000,900"],
        } } } });
        let session = driver.call("POST", "/session", Some(caps)).expect("creating a browser session");
        driver.session = session["value"]["sessionId"].as_str().unwrap_or_else(|| panic!("{session}")).to_owned();
        driver
    }

    fn call(&self, method: &str, path: &str, body: Option<Value>) -> std::io::Result<Value> {
        let body = body.map(|b| b.to_string()).unwrap_or_default();
        let headers = [("Content-Type", "application/json")];
        let r = http_request(self.addr, method, path, &headers, body.as_bytes())?;
        serde_json::from_str(&r.body).map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e))
    }

    fn session(&self, method: &str, path: &str, body: Value) -> Value {
        let v = self.call(method, &format!("/session/{}{path}", self.session), Some(body)).unwrap();
        assert!(v["value"].get("error").is_none(), "{method} {path}: {v}");
        v["value"].clone()
    }

    fn script(&self, script: &str) -> Value {
        self.session("POST", "/execute/sync", json!({ "script": script, "args": [] }))
    }
}

impl Drop for Driver {
    fn drop(&mut self) {
        if !self.session.is_empty() {
            let _ = self.call("DELETE", &format!("/session/{}", self.session), None);
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[test]
fn a_person_uploads_an_image_and_sees_the_angles_and_the_cuboid() {
    // Two categories: the page's selector offers each model the server has (the second is the
    // quick model again, under another category).
    let server = Server::config("web").quick_model().also_as("chair").start();
    let image = quick_images("source", 1).remove(0);
    let expected = server.request("POST", "/v1/pose/car", &[], &image.bytes).json();
    let azimuth = expected["estimates"][0]["azimuth_deg"].as_f64().unwrap();

    let driver = Driver::start();
    driver.session("POST", "/url", json!({ "url": format!("http://{}/", server.http_addr) }));
    wait(&driver, "document.querySelectorAll('#category option').length", |v| v.as_u64() == Some(2));
    let offered = driver.script("return [...document.querySelectorAll('#category option')].map(o => o.value)");
    assert_eq!(offered, json!(["car", "chair"]));
    assert_eq!(driver.script("return document.getElementById('category').value"), "car");
    let input = driver.session("POST", "/element", json!({ "using": "css selector", "value": "#file" }));
    let input = input[ELEMENT].as_str().expect("the file input").to_owned();
    driver.session("POST", &format!("/element/{input}/value"), json!({ "text": image.path.display().to_string() }));

    let status = wait(&driver, "document.getElementById('status').textContent", |v| v != "estimating…" && v != "");
    assert_eq!(status, "done", "{}", server.log());
    let shown = driver.script("return document.getElementById('azimuth_deg').textContent");
    assert_eq!(shown, format!("{azimuth:.1}°"));
    let hidden = driver.script("return document.getElementById('angles').hidden");
    assert_eq!(hidden, false);
    let edges = driver.script("return document.getElementById('overlay').dataset.edges");
    assert_eq!(edges, "12", "all 12 cuboid edges drawn");
    // The overlay's colours are on the canvas: its green and red edge pixels.
    let drawn = driver.script(
        "const c = document.getElementById('overlay'); \
         const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; let n = 0; \
         for (let i = 0; i < d.length; i += 4) { \
           const green = d[i] < 60 && d[i + 1] > 180 && d[i + 2] > 70 && d[i + 2] < 140; \
           const red = d[i] > 220 && d[i + 1] < 90 && d[i + 2] < 80; if (green || red) n++; } \
         return [c.width, c.height, n];",
    );
    assert_eq!((drawn[0].as_u64(), drawn[1].as_u64()), (Some(160), Some(64)), "{drawn}");
    assert!(drawn[2].as_u64().unwrap() > 50, "too few overlay pixels: {drawn}");

    // The browser can take a screenshot of the result (as a person would see it).
    let png = driver.session("GET", "/screenshot", json!({}));
    assert!(png.as_str().is_some_and(|s| s.len() > 1000));
    if let Some(path) = std::env::var_os("UDAPOSE_WEB_SCREENSHOT_B64") {
        std::fs::write(path, png.as_str().unwrap()).unwrap(); // base64 PNG, for a person to look at
    }

    // The page asks for no favicon (a 404 in every log otherwise).
    let icon = driver.script("return document.querySelector('link[rel=icon]').href");
    assert!(icon.as_str().is_some_and(|h| h.starts_with("data:")), "{icon}");

    // A bad file shows the server's message instead, and leaves no unhandled error behind (the
    // browser cannot show it either, after the answer came).
    driver.script(
        "window.unhandled = []; \
         window.addEventListener('unhandledrejection', e => window.unhandled.push(String(e.reason))); return 0;",
    );
    let bad = std::env::temp_dir().join(format!("udapose-web-bad-{}.png", std::process::id()));
    std::fs::write(&bad, b"not really a png").unwrap();
    driver.session("POST", &format!("/element/{input}/value"), json!({ "text": bad.display().to_string() }));
    let status = wait(&driver, "document.getElementById('status').textContent", |v| v != "estimating…" && v != "done");
    let _ = std::fs::remove_file(&bad);
    assert!(status.as_str().unwrap().contains("400 INVALID_ARGUMENT"), "{status}");
    thread::sleep(Duration::from_millis(500));
    let unhandled = driver.script("return window.unhandled");
    assert_eq!(unhandled, json!([]), "uncaught errors on the page");
}

/// Polls a script expression until `done` holds (20 s at most); returns its last value.
fn wait(driver: &Driver, expression: &str, done: impl Fn(&Value) -> bool) -> Value {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let v = driver.script(&format!("return {expression}"));
        if done(&v) {
            return v;
        }
        assert!(Instant::now() < deadline, "{expression} stayed {v}");
        thread::sleep(Duration::from_millis(100));
    }
}
