//! The browser side of `deform live --serve`: the page over HTTP (tiny_http) and a WebSocket
//! per browser (tungstenite) on a port of its own, one thread per connection.
//!
//! Nothing queues between the browser and the solver. The browser's tool positions go into a
//! one-slot [`Mailbox`]: a position the solver has not taken yet is replaced by the newer one
//! and counted as dropped (the lag the page shows). The solver's frames go out the same way:
//! every connection sends the newest frame it has not sent yet, so a slow or vanished browser
//! never holds the solver up, and a browser that reconnects simply starts from the newest.

use std::io::ErrorKind;
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context};
use serde::Deserialize;
use tungstenite::{Message, WebSocket};

const INDEX_HTML: &str = include_str!("../../web/index.html");
const LIVE_JS: &str = include_str!("../../web/live.js");
const THREE_MODULE: &str = include_str!("../../web/vendor/three.module.js");
const THREE_CORE: &str = include_str!("../../web/vendor/three.core.js");
const ORBIT_CONTROLS: &str = include_str!("../../web/vendor/OrbitControls.js");

/// Browsers connected at once; further ones are refused (each costs a thread).
const MAX_CONNECTIONS: usize = 16;
/// How often a connection looks for a newer frame when the browser is silent.
const POLL: Duration = Duration::from_millis(15);
/// A browser that takes longer than this to accept a frame is dropped.
const WRITE_TIMEOUT: Duration = Duration::from_secs(2);

/// What a browser sends, as JSON text messages: `{"type": "tool", "u": [x, y, z]}`,
/// `{"type": "pause", "paused": true}`, `{"type": "reset"}`.
#[derive(Debug)]
pub enum Command {
    /// Move the tool: its displacement from rest, in grid units.
    Tool { u: [f64; 3] },
    /// Stop or resume solving (positions sent while paused are kept, the newest wins).
    Pause { paused: bool },
    /// The tool back to rest.
    Reset,
}

/// A command's JSON as it comes. Not a serde internally tagged enum: those buffer numbers
/// first, which fails for floats with serde_json's `arbitrary_precision` (on in this tree).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct WireCommand {
    #[serde(rename = "type")]
    kind: String,
    u: Option<[f64; 3]>,
    paused: Option<bool>,
}

impl Command {
    pub fn parse(text: &str) -> Result<Command, String> {
        let c: WireCommand = serde_json::from_str(text).map_err(|e| e.to_string())?;
        match (c.kind.as_str(), c.u, c.paused) {
            ("tool", Some(u), None) if u.iter().all(|v| v.is_finite()) => Ok(Command::Tool { u }),
            ("pause", None, Some(paused)) => Ok(Command::Pause { paused }),
            ("reset", None, None) => Ok(Command::Reset),
            _ => Err(format!(
                "not a command: {text:.80} (expected tool with u = [x, y, z], pause with paused, or reset)"
            )),
        }
    }
}

/// The browsers' commands as the solver sees them: one slot for the newest tool position.
#[derive(Debug, Default)]
pub struct Inbox {
    /// The newest position not yet solved, and when it arrived.
    pub tool: Option<([f64; 3], Instant)>,
    pub reset: bool,
    pub paused: bool,
    /// Positions replaced before the solver took them (stale, never solved).
    pub dropped: u64,
}

/// The newest frame, as the JSON every connection sends.
#[derive(Default)]
struct Latest {
    seq: u64,
    json: Arc<String>,
}

/// The one place the solver and the connections meet.
pub struct Mailbox {
    inbox: Mutex<Inbox>,
    wake: Condvar,
    latest: Mutex<Latest>,
    /// Sent first on every connection: the grid, its nodes and the tool nodes.
    mesh: String,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // A connection thread that panicked holding the lock leaves valid data behind.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Mailbox {
    pub fn new(mesh: String) -> Self {
        Mailbox {
            inbox: Mutex::new(Inbox::default()),
            wake: Condvar::new(),
            latest: Mutex::new(Latest::default()),
            mesh,
        }
    }

    fn post(&self, command: Command) {
        let mut inbox = lock(&self.inbox);
        match command {
            Command::Tool { u } => {
                if inbox.tool.is_some() {
                    inbox.dropped += 1;
                }
                inbox.tool = Some((u, Instant::now()));
            }
            Command::Pause { paused } => inbox.paused = paused,
            Command::Reset => {
                inbox.reset = true;
                inbox.tool = None;
            }
        }
        self.wake.notify_all();
    }

    /// Waits up to `timeout` for work (a reset, or a tool position while not paused) and
    /// hands the solver the inbox to take it from.
    pub fn wait(&self, timeout: Duration) -> MutexGuard<'_, Inbox> {
        let inbox = lock(&self.inbox);
        let (inbox, _) = self
            .wake
            .wait_timeout_while(inbox, timeout, |i| {
                !(i.reset || (i.tool.is_some() && !i.paused))
            })
            .unwrap_or_else(|e| e.into_inner());
        inbox
    }

    /// Makes `json` the newest frame.
    pub fn publish(&self, json: String) {
        let mut latest = lock(&self.latest);
        latest.seq += 1;
        latest.json = Arc::new(json);
    }

    fn newer_than(&self, seen: u64) -> Option<(u64, Arc<String>)> {
        let latest = lock(&self.latest);
        (latest.seq > seen).then(|| (latest.seq, latest.json.clone()))
    }
}

/// Where the server listens.
pub struct Bound {
    pub http: SocketAddr,
    pub websocket: SocketAddr,
}

/// Starts the HTTP and WebSocket threads; they run until the process ends.
pub fn start(addr: SocketAddr, mailbox: Arc<Mailbox>) -> anyhow::Result<Bound> {
    let http = tiny_http::Server::http(addr)
        .map_err(|e| anyhow!("cannot listen on {addr}: {e} (give another --addr)"))?;
    let http_addr = http
        .server_addr()
        .to_ip()
        .context("the HTTP server is not on an IP address")?;
    let ws = TcpListener::bind(SocketAddr::new(addr.ip(), 0))
        .with_context(|| format!("cannot open a WebSocket port on {}", addr.ip()))?;
    let ws_addr = ws.local_addr()?;
    let index = INDEX_HTML.replace("__WS_PORT__", &ws_addr.port().to_string());
    std::thread::Builder::new()
        .name("live-http".into())
        .spawn(move || serve_http(http, index))?;
    std::thread::Builder::new()
        .name("live-ws".into())
        .spawn(move || accept_websockets(ws, mailbox))?;
    Ok(Bound {
        http: http_addr,
        websocket: ws_addr,
    })
}

fn serve_http(server: tiny_http::Server, index: String) {
    for request in server.incoming_requests() {
        let (body, mime) = match request.url() {
            "/" | "/index.html" => (index.as_str(), "text/html; charset=utf-8"),
            "/live.js" => (LIVE_JS, "text/javascript"),
            "/vendor/three.module.js" => (THREE_MODULE, "text/javascript"),
            "/vendor/three.core.js" => (THREE_CORE, "text/javascript"),
            "/vendor/OrbitControls.js" => (ORBIT_CONTROLS, "text/javascript"),
            _ => ("not found", "text/plain"),
        };
        let status = if body == "not found" { 404 } else { 200 };
        let header = tiny_http::Header::from_bytes("Content-Type", mime).expect("a valid header");
        let response = tiny_http::Response::from_string(body)
            .with_status_code(status)
            .with_header(header);
        // A browser that went away mid-response is not the server's problem.
        let _ = request.respond(response);
    }
}

fn accept_websockets(listener: TcpListener, mailbox: Arc<Mailbox>) {
    let open = Arc::new(AtomicUsize::new(0));
    for stream in listener.incoming().flatten() {
        if open.load(Ordering::SeqCst) >= MAX_CONNECTIONS {
            eprintln!("live: {MAX_CONNECTIONS} browsers connected already; refused one");
            continue;
        }
        open.fetch_add(1, Ordering::SeqCst);
        let (mailbox, open) = (mailbox.clone(), open.clone());
        let spawned = std::thread::Builder::new()
            .name("live-browser".into())
            .spawn(move || {
                if let Err(e) = connection(stream, &mailbox) {
                    eprintln!("live: browser connection ended: {e:#}");
                }
                open.fetch_sub(1, Ordering::SeqCst);
            });
        if spawned.is_err() {
            eprintln!("live: no thread for another browser; refused it");
        }
    }
}

fn is_timeout(e: &tungstenite::Error) -> bool {
    matches!(e, tungstenite::Error::Io(io) if matches!(io.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut))
}

/// One browser: its commands into the mailbox, the newest frames out.
fn connection(stream: TcpStream, mailbox: &Mailbox) -> anyhow::Result<()> {
    stream.set_read_timeout(Some(WRITE_TIMEOUT))?;
    stream.set_write_timeout(Some(WRITE_TIMEOUT))?;
    let mut ws: WebSocket<TcpStream> =
        tungstenite::accept(stream).map_err(|e| anyhow!("WebSocket handshake: {e}"))?;
    ws.get_ref().set_read_timeout(Some(POLL))?;
    ws.send(Message::text(mailbox.mesh.clone()))?;
    let mut seen = 0;
    loop {
        match ws.read() {
            Ok(Message::Text(text)) => match Command::parse(text.as_str()) {
                Ok(command) => mailbox.post(command),
                Err(e) => {
                    let error = serde_json::json!({ "type": "error", "message": e });
                    ws.send(Message::text(error.to_string()))?;
                }
            },
            Ok(Message::Close(_)) => return Ok(()),
            Ok(_) => {}
            Err(e) if is_timeout(&e) => {}
            // A browser that went away (closed, reloaded, crashed) ends its connection quietly.
            Err(
                tungstenite::Error::ConnectionClosed
                | tungstenite::Error::AlreadyClosed
                | tungstenite::Error::Protocol(
                    tungstenite::error::ProtocolError::ResetWithoutClosingHandshake,
                ),
            ) => return Ok(()),
            Err(e) => return Err(e.into()),
        }
        if let Some((seq, json)) = mailbox.newer_than(seen) {
            seen = seq;
            ws.send(Message::text(json.as_str()))?;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_newer_tool_position_replaces_the_unsolved_one_and_counts_as_dropped() {
        let mailbox = Mailbox::new(String::new());
        for z in [1.0, 2.0, 3.0] {
            mailbox.post(Command::Tool { u: [0.0, 0.0, z] });
        }
        let mut inbox = mailbox.wait(Duration::ZERO);
        assert_eq!(inbox.tool.take().map(|(u, _)| u), Some([0.0, 0.0, 3.0]));
        assert_eq!(inbox.dropped, 2);
    }

    #[test]
    fn paused_holds_the_position_until_resumed() {
        let mailbox = Mailbox::new(String::new());
        mailbox.post(Command::Pause { paused: true });
        mailbox.post(Command::Tool { u: [1.0, 0.0, 0.0] });
        let started = Instant::now();
        let inbox = mailbox.wait(Duration::from_millis(50));
        assert!(inbox.tool.is_some() && inbox.paused);
        assert!(started.elapsed() >= Duration::from_millis(50));
    }

    #[test]
    fn commands_parse_and_malformed_ones_are_refused() {
        assert!(matches!(
            Command::parse(r#"{"type":"tool","u":[0.5,0,-1.25]}"#),
            Ok(Command::Tool {
                u: [0.5, 0.0, -1.25]
            })
        ));
        assert!(matches!(
            Command::parse(r#"{"type":"pause","paused":true}"#),
            Ok(Command::Pause { paused: true })
        ));
        assert!(matches!(
            Command::parse(r#"{"type":"reset"}"#),
            Ok(Command::Reset)
        ));
        for text in [
            "",
            "{}",
            r#"{"type":"tool"}"#,
            r#"{"type":"tool","u":[1,2]}"#,
            r#"{"type":"tool","u":[1,2,"x"]}"#,
            r#"{"type":"reset","u":[1,2,3]}"#,
            r#"{"type":"fly"}"#,
            r#"{"type":"tool","u":[0,0,0],"speed":3}"#,
        ] {
            assert!(Command::parse(text).is_err(), "{text}");
        }
    }
}
