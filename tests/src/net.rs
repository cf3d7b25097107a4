//! Network helpers for end-to-end tests of `canopy-server serve`: start the real binary on a free
//! loopback port, a tiny HTTP/1.1 client, a tiny WebSocket client, a `multipart/byteranges`
//! parser, and an nginx serving the same asset folder. Everything talks to 127.0.0.1 only.

use std::fmt::Write as _;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

/// A running `canopy-server serve`, killed on drop.
#[derive(Debug)]
pub struct Server {
    child: Child,
    /// The bound address.
    pub addr: SocketAddr,
    /// The data folder.
    pub data: PathBuf,
}

impl Server {
    /// Starts `canopy-server serve --data DATA --addr 127.0.0.1:0 ARGS…` and waits (up to 120 s,
    /// which covers a first-start demo bake in a debug build) for its "listening on" line.
    /// Its log is appended to `DATA.log`.
    pub fn start(data: &Path, args: &[&str]) -> Self {
        let log_path = data.with_extension("log");
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log_path)
            .expect("server log");
        let mut child = Command::new(crate::server())
            .arg("serve")
            .arg("--data")
            .arg(data)
            .args(["--addr", "127.0.0.1:0"])
            .args(args)
            .env("RUST_LOG", "info")
            .stdout(Stdio::piped())
            .stderr(log)
            .spawn()
            .expect("spawn canopy-server");
        let stdout = child.stdout.take().expect("stdout");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if let Some(a) = line.strip_prefix("canopy-server listening on http://") {
                    let _ = tx.send(a.trim().to_string());
                }
            }
        });
        let Ok(addr) = rx.recv_timeout(Duration::from_mins(2)) else {
            let _ = child.kill();
            let log = std::fs::read_to_string(&log_path).unwrap_or_default();
            panic!("canopy-server did not start:\n{log}");
        };
        Self {
            child,
            addr: addr.parse().expect("address"),
            data: data.to_path_buf(),
        }
    }

    /// The server's process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Sends SIGTERM and waits (up to 10 s) for a clean exit.
    pub fn stop(mut self) -> ExitStatus {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        let t0 = Instant::now();
        loop {
            if let Ok(Some(s)) = self.child.try_wait() {
                return s;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(10),
                "server did not stop within 10 s of SIGTERM"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// An HTTP response.
#[derive(Debug, Clone)]
pub struct HttpResponse {
    /// Status code.
    pub status: u16,
    /// Headers in order, names lowercased.
    pub headers: Vec<(String, String)>,
    /// Body (de-chunked).
    pub body: Vec<u8>,
}

impl HttpResponse {
    /// The first header of that (lowercase) name.
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
    }

    /// The body as JSON.
    pub fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.body)
            .unwrap_or_else(|e| panic!("not JSON ({e}): {}", String::from_utf8_lossy(&self.body)))
    }
}

fn find(h: &[u8], n: &[u8]) -> Option<usize> {
    h.windows(n.len()).position(|w| w == n)
}

/// One HTTP/1.1 request on a fresh connection (`Connection: close`), 10 s timeout.
pub fn http(addr: SocketAddr, method: &str, path: &str, headers: &[(&str, &str)], body: Option<&[u8]>) -> HttpResponse {
    let mut s = TcpStream::connect(addr).expect("connect");
    s.set_read_timeout(Some(Duration::from_secs(10))).expect("timeout");
    let mut req = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for (k, v) in headers {
        let _ = write!(req, "{k}: {v}\r\n");
    }
    if let Some(b) = body {
        let _ = write!(req, "Content-Length: {}\r\nContent-Type: application/json\r\n", b.len());
    }
    req.push_str("\r\n");
    s.write_all(req.as_bytes()).expect("send");
    if let Some(b) = body {
        s.write_all(b).expect("send body");
    }
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).expect("read response");
    let end = find(&raw, b"\r\n\r\n").expect("response head");
    let head = String::from_utf8_lossy(&raw[..end]).to_string();
    let mut lines = head.split("\r\n");
    let status = lines
        .next()
        .and_then(|l| l.split(' ').nth(1))
        .and_then(|c| c.parse().ok())
        .expect("status line");
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
        .collect();
    let mut body = raw[end + 4..].to_vec();
    if headers
        .iter()
        .any(|(k, v)| k == "transfer-encoding" && v.contains("chunked"))
    {
        body = dechunk(&body);
    }
    HttpResponse { status, headers, body }
}

fn dechunk(mut b: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    while let Some(e) = find(b, b"\r\n") {
        let n = usize::from_str_radix(
            String::from_utf8_lossy(&b[..e]).split(';').next().unwrap_or("0").trim(),
            16,
        )
        .unwrap_or(0);
        if n == 0 {
            break;
        }
        out.extend_from_slice(&b[e + 2..e + 2 + n]);
        b = &b[e + 2 + n + 2..];
    }
    out
}

/// `GET path` with one `Range` header.
pub fn get_range(addr: SocketAddr, path: &str, range: &str) -> HttpResponse {
    http(addr, "GET", path, &[("Range", range)], None)
}

/// Splits a `multipart/byteranges` body into `(first, last, data)` parts.
pub fn multipart_parts(content_type: &str, body: &[u8]) -> Vec<(u64, u64, Vec<u8>)> {
    let boundary = content_type
        .split("boundary=")
        .nth(1)
        .expect("boundary")
        .trim_matches('"');
    let delim = format!("--{boundary}");
    let mut parts = Vec::new();
    let mut rest = body;
    loop {
        let at = find(rest, delim.as_bytes()).expect("delimiter");
        rest = &rest[at + delim.len()..];
        if rest.starts_with(b"--") {
            return parts;
        }
        let head_end = find(rest, b"\r\n\r\n").expect("part head");
        let head = String::from_utf8_lossy(&rest[..head_end]).to_string();
        let cr = head
            .split("\r\n")
            .find_map(|l| {
                l.split_once(':')
                    .filter(|(k, _)| k.eq_ignore_ascii_case("content-range"))
                    .map(|(_, v)| v.trim().to_string())
            })
            .expect("Content-Range in part");
        let (a, b) = cr
            .trim_start_matches("bytes ")
            .split('/')
            .next()
            .and_then(|r| r.split_once('-'))
            .expect("range");
        let (a, b): (u64, u64) = (a.parse().expect("first"), b.parse().expect("last"));
        let data = rest[head_end + 4..head_end + 4 + (b - a + 1) as usize].to_vec();
        rest = &rest[head_end + 4 + data.len()..];
        parts.push((a, b, data));
    }
}

/// A minimal WebSocket client (text frames; enough for presence tests).
#[derive(Debug)]
pub struct WsClient {
    s: TcpStream,
}

/// A received WebSocket message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum WsMessage {
    /// A text frame.
    Text(String),
    /// A close frame: code and reason.
    Close(u16, String),
}

impl WsClient {
    /// Connects and upgrades; returns the HTTP status line's code and the client when it is 101.
    pub fn connect(addr: SocketAddr, path: &str) -> Result<Self, u16> {
        let mut s = TcpStream::connect(addr).expect("connect");
        s.set_read_timeout(Some(Duration::from_secs(10))).expect("timeout");
        let req = format!(
            "GET {path} HTTP/1.1\r\nHost: {addr}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
             Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
        );
        s.write_all(req.as_bytes()).expect("send");
        let mut head = Vec::new();
        let mut byte = [0u8; 1];
        while !head.ends_with(b"\r\n\r\n") {
            s.read_exact(&mut byte).expect("read upgrade response");
            head.push(byte[0]);
        }
        let code: u16 = String::from_utf8_lossy(&head)
            .split(' ')
            .nth(1)
            .and_then(|c| c.parse().ok())
            .unwrap_or(0);
        if code == 101 { Ok(Self { s }) } else { Err(code) }
    }

    /// Sends a masked text frame.
    pub fn send_text(&mut self, text: &str) {
        let p = text.as_bytes();
        let mut f = vec![0x81u8];
        if p.len() < 126 {
            f.push(0x80 | p.len() as u8);
        } else {
            f.push(0x80 | 0x7e);
            f.extend_from_slice(&(p.len() as u16).to_be_bytes());
        }
        let mask = [0x37u8, 0xfa, 0x21, 0x3d];
        f.extend_from_slice(&mask);
        f.extend(p.iter().enumerate().map(|(i, b)| b ^ mask[i % 4]));
        self.s.write_all(&f).expect("send frame");
    }

    /// Receives the next text or close message (skipping pings), with the 10 s read timeout.
    pub fn recv(&mut self) -> Option<WsMessage> {
        loop {
            let mut h = [0u8; 2];
            self.s.read_exact(&mut h).ok()?;
            let opcode = h[0] & 0x0f;
            let mut len = u64::from(h[1] & 0x7f);
            if len == 126 {
                let mut b = [0u8; 2];
                self.s.read_exact(&mut b).ok()?;
                len = u64::from(u16::from_be_bytes(b));
            } else if len == 127 {
                let mut b = [0u8; 8];
                self.s.read_exact(&mut b).ok()?;
                len = u64::from_be_bytes(b);
            }
            let mut p = vec![0u8; len as usize];
            self.s.read_exact(&mut p).ok()?;
            match opcode {
                1 => return Some(WsMessage::Text(String::from_utf8_lossy(&p).to_string())),
                8 => {
                    let code = if p.len() >= 2 {
                        u16::from_be_bytes([p[0], p[1]])
                    } else {
                        1005
                    };
                    return Some(WsMessage::Close(
                        code,
                        String::from_utf8_lossy(p.get(2..).unwrap_or_default()).to_string(),
                    ));
                }
                _ => {}
            }
        }
    }

    /// Receives text messages until one satisfies `pred` (or panics after `limit` messages).
    pub fn recv_until(&mut self, limit: usize, pred: impl Fn(&serde_json::Value) -> bool) -> serde_json::Value {
        for _ in 0..limit {
            match self.recv() {
                Some(WsMessage::Text(t)) => {
                    let v: serde_json::Value = serde_json::from_str(&t).expect("JSON message");
                    if pred(&v) {
                        return v;
                    }
                }
                other => panic!("expected a text message, got {other:?}"),
            }
        }
        panic!("no matching message in {limit} messages");
    }
}

/// A free loopback port (bound, then released).
pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("free port")
}

/// The nginx binary, if installed. With `CI` set a missing nginx panics (the interop test must
/// fail there, not skip); otherwise returns `None` after printing why.
pub fn nginx_binary() -> Option<PathBuf> {
    for p in [
        "nginx",
        "/usr/sbin/nginx",
        "/usr/local/sbin/nginx",
        "/usr/local/nginx/sbin/nginx",
    ] {
        if Command::new(p)
            .arg("-v")
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success())
        {
            return Some(PathBuf::from(p));
        }
    }
    assert!(
        std::env::var_os("CI").is_none(),
        "nginx is missing and CI is set (.ci/run installs it)"
    );
    eprintln!("skipping: nginx is not installed");
    None
}

/// An nginx serving a folder on a loopback port, as a foreground child process; stopped on drop.
#[derive(Debug)]
pub struct Nginx {
    child: Child,
    /// Its address.
    pub addr: SocketAddr,
}

impl Nginx {
    /// Starts nginx (single process, no daemon) with a generated config in `scratch` that serves
    /// `root` the way a static host would; `None` when nginx is not installed (see
    /// [`nginx_binary`]).
    pub fn start(root: &Path, scratch: &Path) -> Option<Self> {
        let bin = nginx_binary()?;
        std::fs::create_dir_all(scratch).expect("nginx scratch");
        let port = free_port();
        let s = scratch.display();
        let conf = format!(
            "daemon off;\nmaster_process off;\nworker_processes 1;\npid {s}/nginx.pid;\nerror_log {s}/error.log warn;\n\
             events {{ worker_connections 256; }}\n\
             http {{\n  access_log off;\n  types {{ }}\n  default_type application/octet-stream;\n  sendfile on;\n\
             \x20 client_body_temp_path {s}/body;\n  proxy_temp_path {s}/proxy;\n  fastcgi_temp_path {s}/fastcgi;\n\
             \x20 uwsgi_temp_path {s}/uwsgi;\n  scgi_temp_path {s}/scgi;\n\
             \x20 server {{\n    listen 127.0.0.1:{port};\n    root {};\n    location /assets/ {{ alias {}/; }}\n  }}\n}}\n",
            root.display(),
            root.display()
        );
        let conf_path = scratch.join("nginx.conf");
        std::fs::write(&conf_path, conf).expect("nginx.conf");
        let child = Command::new(bin)
            .arg("-c")
            .arg(&conf_path)
            .arg("-p")
            .arg(scratch)
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("spawn nginx");
        let addr: SocketAddr = ([127, 0, 0, 1], port).into();
        let t0 = Instant::now();
        while TcpStream::connect(addr).is_err() {
            assert!(
                t0.elapsed() < Duration::from_secs(10),
                "nginx did not start; see {s}/error.log"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        Some(Self { child, addr })
    }
}

impl Drop for Nginx {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
