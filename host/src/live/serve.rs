//! The browser side of `deform live --serve`: the page over HTTP (tiny_http) and a WebSocket
//! per browser (tungstenite) on a port of its own, one thread per connection.
//!
//! Nothing queues between the browser and the solver. The browser's tool positions go into a
//! one-slot [`Mailbox`]: a position the solver has not taken yet is replaced by the newer one
//! and counted as dropped (the lag the page shows). The solver's frames go out the same way:
//! every connection sends the newest frame it has not sent yet, so a slow or vanished browser
//! never holds the solver up, and a browser that reconnects simply starts from the newest.
//!
//! Only the page itself may drive the tool. A browser sends every WebSocket handshake with the
//! `Origin` of the page that opens it, so a page from another site open in the same browser is
//! refused by its `Origin` ([`Guard`]); and every request must name the server by an IP address
//! or `localhost` in its `Host` header, so a site whose DNS name an attacker re-points at this
//! machine (DNS rebinding: the browser then calls the attacker's page same-origin) is refused
//! too. A client that is not a browser sends no `Origin` and is let in: it could open the
//! local port anyway.

use std::io::ErrorKind;
use std::net::{IpAddr, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context};
use serde::Deserialize;
use tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tungstenite::http::uri::{Authority, Uri};
use tungstenite::http::StatusCode;
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

/// Who may talk to the server: requests that name it by IP address or `localhost` on its own
/// port (`Host`), and, for the WebSocket, only from a page this server served (`Origin`).
#[derive(Debug, Clone, Copy)]
pub struct Guard {
    pub http_port: u16,
    pub ws_port: u16,
}

impl Guard {
    /// Checks a request's `Host` header against `port`: the host must be an IP address or
    /// `localhost` (a DNS name could be re-pointed at this machine), the port this server's.
    fn host(&self, host: Option<&str>, port: u16) -> Result<String, String> {
        let host = host.ok_or("no Host header")?;
        let authority: Authority = host
            .parse()
            .map_err(|_| format!("Host {host:?} is not host:port"))?;
        let name = authority
            .host()
            .trim_start_matches('[')
            .trim_end_matches(']');
        if name != "localhost" && name.parse::<IpAddr>().is_err() {
            return Err(format!(
                "Host {host:?} is a DNS name; open the page by IP address or localhost"
            ));
        }
        if authority.port_u16() != Some(port) {
            return Err(format!("Host {host:?} is not this server's port {port}"));
        }
        Ok(name.to_ascii_lowercase())
    }

    /// Checks a WebSocket handshake: `Host` as [`Guard::host`], and an `Origin`, when there is
    /// one (browsers always send it), that is the page's: `http://` the same host, the HTTP port.
    pub fn websocket(&self, host: Option<&str>, origin: Option<&str>) -> Result<(), String> {
        let name = self.host(host, self.ws_port)?;
        let Some(origin) = origin else {
            return Ok(());
        };
        let uri: Uri = origin
            .parse()
            .map_err(|_| format!("Origin {origin:?} is not a URL"))?;
        let origin_name = uri.host().map(|h| {
            h.trim_start_matches('[')
                .trim_end_matches(']')
                .to_ascii_lowercase()
        });
        if uri.scheme_str() != Some("http")
            || origin_name.as_deref() != Some(name.as_str())
            || uri.port_u16() != Some(self.http_port)
        {
            return Err(format!(
                "Origin {origin:?} is not this server's page (http://{name}:{})",
                self.http_port
            ));
        }
        Ok(())
    }

    /// Checks a page request's `Host` (DNS rebinding).
    pub fn page(&self, host: Option<&str>) -> Result<(), String> {
        self.host(host, self.http_port).map(|_| ())
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
    let guard = Guard {
        http_port: http_addr.port(),
        ws_port: ws_addr.port(),
    };
    std::thread::Builder::new()
        .name("live-http".into())
        .spawn(move || serve_http(http, index, guard))?;
    std::thread::Builder::new()
        .name("live-ws".into())
        .spawn(move || accept_websockets(ws, mailbox, guard))?;
    Ok(Bound {
        http: http_addr,
        websocket: ws_addr,
    })
}

fn serve_http(server: tiny_http::Server, index: String, guard: Guard) {
    for request in server.incoming_requests() {
        let host = request
            .headers()
            .iter()
            .find(|h| h.field.equiv("Host"))
            .map(|h| h.value.as_str().to_string());
        if let Err(why) = guard.page(host.as_deref()) {
            let _ = request.respond(tiny_http::Response::from_string(why).with_status_code(403));
            continue;
        }
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

fn accept_websockets(listener: TcpListener, mailbox: Arc<Mailbox>, guard: Guard) {
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
                if let Err(e) = connection(stream, &mailbox, guard) {
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
fn connection(stream: TcpStream, mailbox: &Mailbox, guard: Guard) -> anyhow::Result<()> {
    stream.set_read_timeout(Some(WRITE_TIMEOUT))?;
    stream.set_write_timeout(Some(WRITE_TIMEOUT))?;
    // The closure's signature is tungstenite's handshake callback's (its error is a whole HTTP
    // response).
    #[allow(clippy::result_large_err)]
    let check = |request: &Request, response: Response| -> Result<Response, ErrorResponse> {
        let header = |name: &str| request.headers().get(name).and_then(|v| v.to_str().ok());
        match guard.websocket(header("Host"), header("Origin")) {
            Ok(()) => Ok(response),
            Err(why) => {
                let mut refusal = ErrorResponse::new(Some(why));
                *refusal.status_mut() = StatusCode::FORBIDDEN;
                Err(refusal)
            }
        }
    };
    let mut ws: WebSocket<TcpStream> =
        tungstenite::accept_hdr(stream, check).map_err(|e| anyhow!("WebSocket handshake: {e}"))?;
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
    fn only_the_pages_origin_and_an_address_or_localhost_host_are_let_in() {
        let guard = Guard {
            http_port: 8080,
            ws_port: 9000,
        };
        for (host, origin) in [
            ("127.0.0.1:9000", Some("http://127.0.0.1:8080")),
            ("localhost:9000", Some("http://localhost:8080")),
            ("[::1]:9000", Some("http://[::1]:8080")),
            ("10.0.0.5:9000", Some("http://10.0.0.5:8080")),
            ("127.0.0.1:9000", None),
        ] {
            guard
                .websocket(Some(host), origin)
                .unwrap_or_else(|e| panic!("{host} {origin:?}: {e}"));
        }
        for (host, origin, why) in [
            (
                "127.0.0.1:9000",
                Some("http://evil.example"),
                "not this server's page",
            ),
            (
                "127.0.0.1:9000",
                Some("http://127.0.0.1:8081"),
                "not this server's page",
            ),
            (
                "127.0.0.1:9000",
                Some("https://127.0.0.1:8080"),
                "not this server's page",
            ),
            (
                "127.0.0.1:9000",
                Some("http://localhost:8080"),
                "not this server's page",
            ),
            ("127.0.0.1:9000", Some("null"), "not"),
            (
                "evil.example:9000",
                Some("http://evil.example:8080"),
                "DNS name",
            ),
            ("127.0.0.1:9001", Some("http://127.0.0.1:8080"), "port 9000"),
        ] {
            let e = guard.websocket(Some(host), origin).unwrap_err();
            assert!(e.contains(why), "{host} {origin:?}: {e}");
        }
        assert!(guard.websocket(None, None).is_err());
        guard.page(Some("127.0.0.1:8080")).unwrap();
        assert!(guard
            .page(Some("rebound.example:8080"))
            .unwrap_err()
            .contains("DNS name"));
    }

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
