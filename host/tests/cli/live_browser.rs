//! `deform live --serve` end to end in a real browser: the firmware in QEMU solves, Debian's
//! headless Chromium (installed by `cargo xtask setup`) shows the page, driven over the Chrome
//! DevTools Protocol with the tungstenite WebSocket the server already builds (no WebDriver
//! client crate to compile). Synthetic key presses move the tool; the force on the page must
//! equal the host's converged f64 reaction force for the tool position the page shows. With a
//! force tool the keys set the load and the page's motion must equal the host's.

use std::io::{BufRead, BufReader, Read};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use base64::Engine;
use deform_host::encode::EncodeOptions;
use deform_host::live::LiveSetup;
use deform_host::reference::max_abs;
use deform_host::scenario::Scenario;
use serde_json::{json, Value};
use tungstenite::stream::MaybeTlsStream;
use tungstenite::{Message, WebSocket};

const SCENARIO: &str = "../examples/needle-insertion.toml";
const FORCE_SCENARIO: &str = "../examples/probe-force-8b.toml";

/// A process and the process group it leads (QEMU and Chromium's helpers), killed on drop; and,
/// should this test process die first, killed by the kernel with it (hil-sim's `child::spawn`).
pub(crate) struct Group(Child);

impl Drop for Group {
    fn drop(&mut self) {
        let pgid = format!("-{}", self.0.id());
        let _ = Command::new("kill").args(["-KILL", "--", &pgid]).status();
        let _ = self.0.wait();
    }
}

fn spawn_group(mut cmd: Command) -> Group {
    use std::os::unix::process::CommandExt;
    let program = format!("{:?}", cmd.get_program());
    cmd.process_group(0);
    Group(
        deform_hil_sim::child::spawn(cmd)
            .unwrap_or_else(|e| panic!("{program} does not start: {e}")),
    )
}

/// Lines of `pipe`, read on a thread (so the pipe never fills up) and handed over a channel.
fn lines(pipe: impl Read + Send + 'static) -> mpsc::Receiver<String> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(pipe).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    rx
}

/// The first line with `marker`, its text from the marker on.
fn wait_for(rx: &mpsc::Receiver<String>, marker: &str, within: Duration, what: &str) -> String {
    let deadline = Instant::now() + within;
    let mut seen = Vec::new();
    while let Some(left) = deadline.checked_duration_since(Instant::now()) {
        match rx.recv_timeout(left) {
            Ok(line) => match line.find(marker) {
                Some(at) => return line[at..].to_string(),
                None => seen.push(line),
            },
            Err(_) => break,
        }
    }
    panic!(
        "{what}: no line with {marker:?} within {within:?}; got:\n{}",
        seen.join("\n")
    );
}

fn chromium() -> PathBuf {
    ["/usr/bin/chromium", "/usr/bin/chromium-browser"]
        .iter()
        .map(PathBuf::from)
        .find(|p| p.exists())
        .expect("Chromium is missing: `cargo xtask setup` installs Debian's chromium")
}

/// A Chrome DevTools Protocol session on one page.
struct Cdp {
    socket: WebSocket<MaybeTlsStream<TcpStream>>,
    session: Option<String>,
    next: u64,
}

impl Cdp {
    fn connect(url: &str) -> Cdp {
        let (socket, _) = tungstenite::connect(url).expect("the DevTools WebSocket");
        if let MaybeTlsStream::Plain(s) = socket.get_ref() {
            s.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
        }
        Cdp {
            socket,
            session: None,
            next: 0,
        }
    }

    fn call(&mut self, method: &str, params: Value) -> Value {
        self.next += 1;
        let mut message = json!({ "id": self.next, "method": method, "params": params });
        if let Some(s) = &self.session {
            message["sessionId"] = json!(s);
        }
        self.socket
            .send(Message::text(message.to_string()))
            .unwrap();
        loop {
            let reply = self.socket.read().expect("a DevTools reply");
            let Message::Text(text) = reply else { continue };
            let v: Value = serde_json::from_str(text.as_str()).unwrap();
            if v["id"] == json!(self.next) {
                assert!(v.get("error").is_none(), "{method}: {v}");
                return v["result"].clone();
            }
        }
    }

    fn eval(&mut self, expression: &str) -> Value {
        let r = self.call(
            "Runtime.evaluate",
            json!({ "expression": expression, "returnByValue": true }),
        );
        assert!(r.get("exceptionDetails").is_none(), "{expression}: {r}");
        r["result"]["value"].clone()
    }

    /// The page's #readout data- attributes.
    fn readout(&mut self) -> Value {
        self.eval("Object.assign({}, document.getElementById('readout')?.dataset ?? {})")
    }

    /// Drags with the left button from `from` by `by` CSS pixels, in a few moves.
    fn drag(&mut self, from: [f64; 2], by: [f64; 2]) {
        let at = |s: f64| json!({ "x": from[0] + s * by[0], "y": from[1] + s * by[1] });
        let event = |kind: &str, s: f64, buttons: u8| {
            let mut e = at(s);
            e["type"] = json!(kind);
            e["button"] = json!("left");
            e["buttons"] = json!(buttons);
            e["clickCount"] = json!(1);
            e
        };
        self.call("Input.dispatchMouseEvent", event("mouseMoved", 0.0, 0));
        self.call("Input.dispatchMouseEvent", event("mousePressed", 0.0, 1));
        for step in 1..=4 {
            let s = f64::from(step) / 4.0;
            self.call("Input.dispatchMouseEvent", event("mouseMoved", s, 1));
        }
        self.call("Input.dispatchMouseEvent", event("mouseReleased", 1.0, 0));
    }

    fn key(&mut self, key: &str, code: u32) {
        for kind in ["keyDown", "keyUp"] {
            self.call(
                "Input.dispatchKeyEvent",
                json!({ "type": kind, "key": key, "code": key, "windowsVirtualKeyCode": code }),
            );
        }
    }

    /// Polls the readout until `done` holds.
    fn until(&mut self, within: Duration, what: &str, done: impl Fn(&Value) -> bool) -> Value {
        let deadline = Instant::now() + within;
        loop {
            let r = self.readout();
            if done(&r) {
                return r;
            }
            assert!(Instant::now() < deadline, "{what} within {within:?}: {r}");
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

fn numbers(v: &Value) -> Vec<f64> {
    v.as_str()
        .unwrap_or_else(|| panic!("not a string: {v}"))
        .split(',')
        .map(|x| x.parse().unwrap())
        .collect()
}

fn number(v: &Value) -> f64 {
    numbers(v)[0]
}

/// The host's converged reaction force and max |u| component for the tool at `u`.
fn reference(u: [f64; 3]) -> ([f64; 3], f64) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(SCENARIO);
    let s = Scenario::load(&path, None).unwrap();
    let spec = s.simulation.as_ref().unwrap().spec_at(&s.model, 0.0);
    let setup = LiveSetup::new(&spec, &EncodeOptions::default()).unwrap();
    let (field, force) = setup.converged(&vec![u; setup.tools.len()], None).unwrap();
    (force, field.iter().map(|v| max_abs(v)).fold(0.0, f64::max))
}

/// `deform live SCENARIO --serve` on a free port with `args` added: the server (killed on
/// drop), the page's address and the WebSocket's port, once it serves.
pub(crate) fn serve(scenario: &Path, args: &[&str]) -> (Group, String, u16) {
    let mut command = Command::new(env!("CARGO_BIN_EXE_deform"));
    command
        .arg("live")
        .arg(scenario)
        .args(["--serve", "--addr", "127.0.0.1:0"])
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit());
    let mut server = spawn_group(command);
    let out = lines(server.0.stdout.take().unwrap());
    let serving = wait_for(
        &out,
        "http://",
        Duration::from_secs(180),
        "deform live --serve",
    );
    let page = serving.split_whitespace().next().unwrap().to_string();
    let ws_port: u16 = serving
        .split("WebSocket on port ")
        .nth(1)
        .and_then(|s| s.split(')').next())
        .and_then(|p| p.parse().ok())
        .unwrap_or_else(|| panic!("no WebSocket port in {serving:?}"));
    (server, page, ws_port)
}

/// Headless Chromium (profile directory `profile` under the test's scratch directory) with
/// `page` open, and a DevTools session on it.
fn open(page: &str, profile: &str) -> (Group, Cdp) {
    let profile = Path::new(env!("CARGO_TARGET_TMPDIR")).join(profile);
    let _ = std::fs::remove_dir_all(&profile);
    std::fs::create_dir_all(&profile).unwrap();
    let mut command = Command::new(chromium());
    command
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            // Containers often have a small /dev/shm.
            "--disable-dev-shm-usage",
            // WebGL in software, since there is no GPU.
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--window-size=1200,800",
            "--remote-debugging-port=0",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg("about:blank")
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let mut browser = spawn_group(command);
    let err = lines(browser.0.stderr.take().unwrap());
    let devtools = wait_for(&err, "ws://", Duration::from_secs(60), "chromium");
    let mut cdp = Cdp::connect(devtools.trim());
    let target = cdp.call("Target.createTarget", json!({ "url": page }));
    let attached = cdp.call(
        "Target.attachToTarget",
        json!({ "targetId": target["targetId"], "flatten": true }),
    );
    cdp.session = Some(attached["sessionId"].as_str().unwrap().to_string());
    (browser, cdp)
}

#[test]
fn the_page_shows_the_targets_force_for_the_tool_the_keys_moved() {
    let started = Instant::now();
    let (mut server, page, ws_port) = serve(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join(SCENARIO),
        &["--tol", "1e-6"],
    );

    // A misbehaving client first: garbage gets an error message, then it vanishes mid-session.
    {
        let (mut rogue, _) =
            tungstenite::connect(format!("ws://127.0.0.1:{ws_port}/")).expect("the WebSocket");
        let mesh = rogue.read().unwrap();
        assert!(mesh.to_text().unwrap().contains("\"mesh\""), "{mesh:?}");
        rogue.send(Message::text("{\"type\":\"fly\"}")).unwrap();
        loop {
            let m = rogue.read().unwrap();
            if m.to_text().unwrap().contains("\"error\"") {
                break;
            }
        }
    }

    let (browser, mut cdp) = open(&page, "chromium-profile");

    let first = cdp.until(Duration::from_secs(60), "a first frame", |r| {
        r["frame"].is_string() && r["connected"] == json!("true")
    });
    assert_eq!(first["solver"], json!("target"), "{first}");
    let u_max_before = number(&first["uMax"]);

    // Six presses of ↓ and one of →: the needle 1.2 grid units down, 0.2 across.
    for _ in 0..6 {
        cdp.key("ArrowDown", 40);
    }
    cdp.key("ArrowRight", 39);
    let moved = cdp.until(
        Duration::from_secs(60),
        "the frame for the moved tool",
        |r| r["tool"] == json!("0.2,0,-1.2"),
    );
    assert!(
        moved.get("error").is_none(),
        "the server refused a command: {moved}"
    );
    let tool = numbers(&moved["tool"]);
    let shown = numbers(&moved["force"]);
    let (want, u_max) = reference([tool[0], tool[1], tool[2]]);
    let scale = want.iter().fold(0f64, |m, v| m.max(v.abs()));
    assert!(scale > 0.1, "the push gives a force: {want:?}");
    for d in 0..3 {
        assert!(
            (shown[d] - want[d]).abs() <= 1e-3 * scale,
            "force {shown:?} on the page, {want:?} from the host"
        );
    }
    let u_max_after = number(&moved["uMax"]);
    assert!(
        (u_max_after - u_max_before).abs() > 0.1,
        "the field changed: max |u| {u_max_before} → {u_max_after}"
    );
    assert!(
        (u_max_after - u_max).abs() <= 1e-3 * u_max,
        "max |u| {u_max_after} on the page, {u_max} from the host"
    );
    // The superposed start (target-core/src/superpose.rs) is exact for the linear springs:
    // the frame may need no iteration at all, but it always costs the target cycles.
    assert!(number(&moved["iterations"]) >= 0.0 && number(&moved["cycles"]) > 0.0);
    println!(
        "moved frame: tool {tool:?}, force {shown:?} (host {want:?}), {} iterations, {} cycles",
        moved["iterations"], moved["cycles"]
    );

    // Let the page render the frame, then keep a screenshot of it.
    std::thread::sleep(Duration::from_millis(500));
    let shot = cdp.call("Page.captureScreenshot", json!({ "format": "png" }));
    let png = base64::engine::general_purpose::STANDARD
        .decode(shot["data"].as_str().unwrap())
        .unwrap();
    assert!(png.starts_with(b"\x89PNG\r\n\x1a\n") && png.len() > 10_000);
    let path = Path::new(env!("CARGO_TARGET_TMPDIR")).join("live.png");
    std::fs::write(&path, &png).unwrap();

    // Paused: a key press moves the tool on the page but nothing is solved until resumed.
    cdp.key(" ", 32);
    let paused = cdp.until(Duration::from_secs(60), "the pause", |r| {
        r["paused"] == json!("true")
    });
    cdp.key("ArrowDown", 40);
    std::thread::sleep(Duration::from_millis(500));
    let still = cdp.readout();
    assert_eq!(
        still["frame"], paused["frame"],
        "solved while paused: {still}"
    );
    assert_eq!(still["requested"], json!("0.2,0,-1.4"), "{still}");
    cdp.key(" ", 32);
    cdp.until(Duration::from_secs(60), "the resumed frame", |r| {
        r["paused"] == json!("false") && r["tool"] == json!("0.2,0,-1.4")
    });

    // The mouse: drag the tool 80 px to the right on the screen; the tool moves and the force
    // shown is again the host's for wherever it ended up.
    let xy = numbers(&cdp.readout()["toolScreen"]);
    cdp.drag([xy[0], xy[1]], [80.0, 0.0]);
    let dragged = cdp.until(Duration::from_secs(60), "the dragged frame", |r| {
        r["requested"] != json!("0.2,0,-1.4") && r["tool"] == r["requested"]
    });
    println!(
        "dragged: {} frames solved in all, {} tool positions dropped as stale, frames/s {}",
        dragged["frame"], dragged["dropped"], dragged["fps"]
    );
    let tool = numbers(&dragged["tool"]);
    assert!(
        (tool[0] - 0.2).abs() > 0.3,
        "the drag moved the tool: {tool:?}"
    );
    let (want, _) = reference([tool[0], tool[1], tool[2]]);
    let shown = numbers(&dragged["force"]);
    let scale = want.iter().fold(0f64, |m, v| m.max(v.abs()));
    for d in 0..3 {
        assert!(
            (shown[d] - want[d]).abs() <= 1e-3 * scale,
            "after the drag: force {shown:?} on the page, {want:?} from the host"
        );
    }

    // A reload (as a second tab) starts from the server's state: the handle where the frames
    // say the tool is, not at rest under a mesh and readout that show it moved.
    cdp.call("Page.reload", json!({}));
    let reloaded = cdp.until(Duration::from_secs(60), "frames after a reload", |r| {
        r["frame"].is_string() && r["connected"] == json!("true") && r["handle"].is_string()
    });
    assert_eq!(reloaded["handle"], dragged["tool"], "{reloaded}");
    assert_ne!(reloaded["handle"], json!("0,0,0"));

    // Reset puts the tool back at rest: no force.
    cdp.key("r", 82);
    let rest = cdp.until(Duration::from_secs(60), "the reset frame", |r| {
        r["tool"] == json!("0,0,0")
    });
    assert!(numbers(&rest["force"])
        .iter()
        .all(|f| f.abs() <= 1e-3 * scale));

    // A reload is a disconnect and a reconnect: the server goes on.
    cdp.call("Page.reload", json!({}));
    cdp.until(Duration::from_secs(60), "frames after a reload", |r| {
        r["frame"].is_string() && r["connected"] == json!("true")
    });
    assert!(
        server.0.try_wait().unwrap().is_none(),
        "the server is still up"
    );
    assert!(
        cdp.readout().get("error").is_none(),
        "no command was refused"
    );
    drop(browser);
    println!(
        "screenshot {} ({} bytes); test took {:.1} s",
        path.display(),
        png.len(),
        started.elapsed().as_secs_f64()
    );
}

/// A force tool in the browser (examples/probe-force-8b.toml): the keys set the load, and the
/// page shows the target's mean tool displacement, equal to the host's converged one.
#[test]
fn the_page_shows_the_targets_motion_for_the_load_the_keys_set() {
    let (_server, page, _) = serve(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join(FORCE_SCENARIO),
        &["--tol", "1e-6"],
    );
    let (browser, mut cdp) = open(&page, "chromium-profile-force");
    let first = cdp.until(Duration::from_secs(60), "a first frame", |r| {
        r["frame"].is_string() && r["connected"] == json!("true")
    });
    assert_eq!(first["kind"], json!("force"), "{first}");
    // Five presses of ↓ and two of →: a load of (0.4, 0, −1) N.
    for _ in 0..5 {
        cdp.key("ArrowDown", 40);
    }
    cdp.key("ArrowRight", 39);
    cdp.key("ArrowRight", 39);
    let moved = cdp.until(Duration::from_secs(60), "the frame for the load", |r| {
        r["tool"] == json!("0.4,0,-1")
    });
    assert!(moved.get("error").is_none(), "{moved}");
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(FORCE_SCENARIO);
    let s = Scenario::load(&path, None).unwrap();
    let sim = s.simulation.as_ref().unwrap();
    let setup = LiveSetup::for_simulation(&s.model, sim, &EncodeOptions::default()).unwrap();
    let (field, want) = setup.converged(&[[0.4, 0.0, -1.0]], None).unwrap();
    let u_max = field.iter().map(|v| max_abs(v)).fold(0.0, f64::max);
    let shown = numbers(&moved["force"]);
    assert!(
        want[2] < -0.01 && want[0] > 0.0,
        "the load moves the probe: {want:?}"
    );
    for d in 0..3 {
        assert!(
            (shown[d] - want[d]).abs() <= 1e-3 * u_max,
            "motion {shown:?} on the page, {want:?} from the host"
        );
    }
    println!("force tool: load (0.4, 0, -1) N, motion {shown:?} m (host {want:?})");
    drop(browser);
}

/// Only the page itself drives the tool: a WebSocket handshake whose `Origin` is another site's
/// (a page open in the same browser) is refused, and so is one that names the server by a DNS
/// name (DNS rebinding), and the page by such a name; the page's own origin, by IP address or
/// `localhost`, is let in. No browser needed: the handshakes are made by hand.
#[test]
fn the_websocket_refuses_other_origins_and_dns_names() {
    use tungstenite::client::IntoClientRequest;
    let (_server, page, ws_port) = serve(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join(SCENARIO),
        &["--target", "host"],
    );
    let http_port: u16 = page
        .trim_end_matches('/')
        .rsplit(':')
        .next()
        .and_then(|p| p.parse().ok())
        .unwrap_or_else(|| panic!("no port in {page}"));
    let handshake = |host: &str, origin: Option<&str>| {
        let mut request = format!("ws://127.0.0.1:{ws_port}/")
            .into_client_request()
            .unwrap();
        request.headers_mut().insert("Host", host.parse().unwrap());
        if let Some(origin) = origin {
            request
                .headers_mut()
                .insert("Origin", origin.parse().unwrap());
        }
        let stream = TcpStream::connect(("127.0.0.1", ws_port)).unwrap();
        // The refusal's HTTP status, if refused.
        match tungstenite::client(request, stream) {
            Ok(_) => Ok(()),
            Err(tungstenite::HandshakeError::Failure(tungstenite::Error::Http(response))) => {
                Err(Some(response.status().as_u16()))
            }
            Err(_) => Err(None),
        }
    };
    let own = format!("http://127.0.0.1:{http_port}");
    let host = format!("127.0.0.1:{ws_port}");
    handshake(&host, Some(&own)).expect("the page's own origin");
    handshake(
        &format!("localhost:{ws_port}"),
        Some(&format!("http://localhost:{http_port}")),
    )
    .expect("localhost");
    for (host, origin) in [
        (host.clone(), Some("http://evil.example".to_string())),
        (
            host.clone(),
            Some(format!("http://127.0.0.1:{}", http_port + 1)),
        ),
        (
            format!("evil.example:{ws_port}"),
            Some(format!("http://evil.example:{http_port}")),
        ),
    ] {
        assert_eq!(
            handshake(&host, origin.as_deref()),
            Err(Some(403)),
            "{host} {origin:?}"
        );
    }
    // The page, asked for by a DNS name that points here.
    let mut stream = TcpStream::connect(("127.0.0.1", http_port)).unwrap();
    std::io::Write::write_all(
        &mut stream,
        format!("GET / HTTP/1.1\r\nHost: rebound.example:{http_port}\r\nConnection: close\r\n\r\n")
            .as_bytes(),
    )
    .unwrap();
    let mut answer = String::new();
    stream.read_to_string(&mut answer).unwrap();
    assert!(answer.starts_with("HTTP/1.1 403"), "{answer:.200}");
}
