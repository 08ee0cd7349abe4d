//! The HTTP server of `f3g view`: a fixed table of in-memory files served to browsers on this
//! machine (or, with `--host`, the network), written on `std::net` so that every connection has
//! its own thread, deadlines and limits.
//!
//! Rules, each for a reason:
//! - One request per connection (`Connection: close`), each connection on a thread of its own,
//!   at most [`MAX_CONNECTIONS`] at once (beyond that the listener's backlog waits): a client
//!   that stalls costs its own connection only.
//! - The request head must arrive within [`HEAD_DEADLINE`] and [`MAX_HEAD`] bytes; every write
//!   must progress within [`WRITE_TIMEOUT`]. A request body is never read.
//! - `GET` and `HEAD` only (405 otherwise); the target must be a path (`/…`, 400 otherwise).
//! - The `Host` header must name this server: `localhost` or an IP address that is loopback or
//!   the address it listens on (any IP address when it listens on all of them), else 421. A
//!   DNS name other than `localhost` is what a DNS-rebinding page would send, so none is
//!   accepted.
//! - `Range: bytes=…` (one range) is answered 206 with that part (416 when it is outside the
//!   file), so a player can stream the avatar; several ranges get the whole file (200), as
//!   HTTP allows.
//! - Anything not in the table is 404: nothing is read from the disk while serving.

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::net::{IpAddr, SocketAddr, TcpListener, TcpStream};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// Connections served at once; further ones wait in the listener's backlog.
pub const MAX_CONNECTIONS: usize = 256;
/// The whole request head must arrive within this time (a per-read timeout alone would let a
/// client trickle one byte at a time).
pub const HEAD_DEADLINE: Duration = Duration::from_secs(10);
/// A write that makes no progress for this long ends the connection.
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(10);
/// The largest request head (request line and headers) read.
pub const MAX_HEAD: usize = 16 * 1024;

/// What is served: path (without the leading `/`; `index.html` for `/`) → bytes.
pub struct Site {
    files: BTreeMap<String, Vec<u8>>,
    /// The address the server listens on (for the `Host` check).
    address: SocketAddr,
}

impl Site {
    pub fn new(files: BTreeMap<String, Vec<u8>>, address: SocketAddr) -> Self {
        Self { files, address }
    }
}

/// An answer: status, headers, and the body to send (empty for `HEAD` and errors without one).
#[derive(Debug, PartialEq)]
pub struct Response<'a> {
    pub status: u16,
    pub headers: Vec<(&'static str, String)>,
    pub body: &'a [u8],
}

impl<'a> Response<'a> {
    fn error(status: u16) -> Self {
        Self {
            status,
            headers: vec![("Content-Type", "text/plain; charset=utf-8".into())],
            body: reason(status).as_bytes(),
        }
    }
}

fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        206 => "Partial Content",
        400 => "Bad Request",
        404 => "Not Found",
        405 => "Method Not Allowed",
        408 => "Request Timeout",
        416 => "Range Not Satisfiable",
        421 => "Misdirected Request",
        431 => "Request Header Fields Too Large",
        _ => "Error",
    }
}

/// Serves `site` on `listener` until the process ends.
pub fn serve(listener: TcpListener, site: Site) -> std::io::Result<()> {
    let site = Arc::new(site);
    let active = Arc::new(AtomicUsize::new(0));
    for stream in listener.incoming() {
        // A connection that failed before it was accepted is the client's problem.
        let Ok(stream) = stream else { continue };
        // Wait for a free slot rather than refuse: the backlog holds the rest.
        while active.load(Ordering::Acquire) >= MAX_CONNECTIONS {
            std::thread::sleep(Duration::from_millis(5));
        }
        active.fetch_add(1, Ordering::AcqRel);
        let slot = Slot(active.clone());
        let site = site.clone();
        // Where no thread can be made (the system's limit), the closure is dropped with its
        // connection and its slot.
        let _ = std::thread::Builder::new()
            .name("f3g-view-connection".into())
            .stack_size(256 * 1024)
            .spawn(move || {
                let _slot = slot;
                // A client that went away or stalled is not the server's problem.
                let _ = connection(stream, &site);
            });
    }
    Ok(())
}

/// A connection's place in the count of those served at once, given back when it ends.
struct Slot(Arc<AtomicUsize>);

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

/// One connection: read the head within its deadline, answer, close.
fn connection(mut stream: TcpStream, site: &Site) -> std::io::Result<()> {
    stream.set_write_timeout(Some(WRITE_TIMEOUT))?;
    let response = match read_head(&mut stream) {
        Ok(head) => answer(site, &head),
        Err(status) => Response::error(status),
    };
    write_response(&mut stream, &response)?;
    stream.flush()?;
    // Tell the client there is no more; what it still sends (a body) is not read.
    stream.shutdown(std::net::Shutdown::Write)
}

/// The request head (up to the blank line), or the status to answer instead.
fn read_head(stream: &mut TcpStream) -> Result<Vec<u8>, u16> {
    let started = Instant::now();
    let mut head = Vec::with_capacity(1024);
    let mut chunk = [0u8; 2048];
    loop {
        let left = HEAD_DEADLINE.saturating_sub(started.elapsed());
        if left.is_zero() {
            return Err(408);
        }
        stream.set_read_timeout(Some(left)).map_err(|_| 400u16)?;
        let n = match stream.read(&mut chunk) {
            Ok(0) => return Err(400),
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                return Err(408);
            }
            Err(_) => return Err(400),
        };
        head.extend_from_slice(&chunk[..n]);
        if let Some(end) = head.windows(4).position(|w| w == b"\r\n\r\n") {
            head.truncate(end);
            return Ok(head);
        }
        if head.len() > MAX_HEAD {
            return Err(431);
        }
    }
}

/// The answer to a request head (without its final blank line).
pub fn answer<'a>(site: &'a Site, head: &[u8]) -> Response<'a> {
    let Ok(head) = std::str::from_utf8(head) else {
        return Response::error(400);
    };
    let mut lines = head.split("\r\n");
    let mut request_line = lines.next().unwrap_or("").split(' ');
    let (Some(method), Some(target), Some(version), None) = (
        request_line.next(),
        request_line.next(),
        request_line.next(),
        request_line.next(),
    ) else {
        return Response::error(400);
    };
    if !version.starts_with("HTTP/1.") {
        return Response::error(400);
    }
    if method != "GET" && method != "HEAD" {
        let mut r = Response::error(405);
        r.headers.push(("Allow", "GET, HEAD".into()));
        return r;
    }
    if !target.starts_with('/') {
        return Response::error(400);
    }
    let mut host = None;
    let mut range = None;
    for line in lines {
        let Some((name, value)) = line.split_once(':') else {
            return Response::error(400);
        };
        let value = value.trim();
        if name.eq_ignore_ascii_case("host") {
            if host.is_some() {
                return Response::error(400);
            }
            host = Some(value);
        } else if name.eq_ignore_ascii_case("range") {
            range = Some(value);
        }
    }
    match host {
        Some(host) if names_this_server(host, site.address) => {}
        _ => return Response::error(421),
    }
    let key = table_key(target);
    let Some(bytes) = site.files.get(&key) else {
        return Response::error(404);
    };
    let mut headers = vec![
        ("Content-Type", content_type(&key).to_string()),
        ("Accept-Ranges", "bytes".into()),
    ];
    let (status, body) = match range.map(|r| byte_range(r, bytes.len() as u64)) {
        Some(RangeRequest::Part(start, end)) => {
            headers.push((
                "Content-Range",
                format!("bytes {start}-{}/{}", end - 1, bytes.len()),
            ));
            (206, &bytes[start as usize..end as usize])
        }
        Some(RangeRequest::Unsatisfiable) => {
            let mut r = Response::error(416);
            r.headers
                .push(("Content-Range", format!("bytes */{}", bytes.len())));
            return r;
        }
        Some(RangeRequest::Whole) | None => (200, bytes.as_slice()),
    };
    // HEAD: the headers GET would send (Content-Length included), no body.
    headers.push(("Content-Length", body.len().to_string()));
    Response {
        status,
        headers,
        body: if method == "HEAD" { &[] } else { body },
    }
}

fn write_response(stream: &mut TcpStream, r: &Response) -> std::io::Result<()> {
    let mut head = format!("HTTP/1.1 {} {}\r\n", r.status, reason(r.status));
    let has_length = r.headers.iter().any(|(n, _)| *n == "Content-Length");
    for (name, value) in &r.headers {
        head.push_str(&format!("{name}: {value}\r\n"));
    }
    if !has_length {
        head.push_str(&format!("Content-Length: {}\r\n", r.body.len()));
    }
    head.push_str("Cache-Control: no-store\r\nConnection: close\r\n\r\n");
    stream.write_all(head.as_bytes())?;
    stream.write_all(r.body)
}

/// Whether a `Host` header names this server (module docs).
fn names_this_server(host: &str, address: SocketAddr) -> bool {
    // `name[:port]`, or `[v6][:port]`.
    let (name, port) = if let Some(rest) = host.strip_prefix('[') {
        let Some((name, after)) = rest.split_once(']') else {
            return false;
        };
        (name, after.strip_prefix(':'))
    } else {
        match host.rsplit_once(':') {
            Some((name, port)) => (name, Some(port)),
            None => (host, None),
        }
    };
    if let Some(port) = port
        && port.parse::<u16>() != Ok(address.port())
    {
        return false;
    }
    if name.eq_ignore_ascii_case("localhost") {
        return true;
    }
    let Ok(ip) = name.parse::<IpAddr>() else {
        return false;
    };
    ip.is_loopback() || ip == address.ip() || address.ip().is_unspecified()
}

/// A `Range` header's meaning for a file of `len` bytes.
#[derive(Debug, PartialEq)]
enum RangeRequest {
    /// Bytes `[start, end)`.
    Part(u64, u64),
    /// Not one byte range this server answers with a part: the whole file.
    Whole,
    /// A range that starts past the end (416).
    Unsatisfiable,
}

fn byte_range(header: &str, len: u64) -> RangeRequest {
    let Some(spec) = header.trim().strip_prefix("bytes=") else {
        return RangeRequest::Whole;
    };
    if spec.contains(',') {
        return RangeRequest::Whole;
    }
    let Some((first, last)) = spec.trim().split_once('-') else {
        return RangeRequest::Whole;
    };
    let parse = |s: &str| s.trim().parse::<u64>().ok();
    match (first.trim().is_empty(), parse(first), parse(last)) {
        // `bytes=-n`: the last n bytes.
        (true, _, Some(n)) if n > 0 => RangeRequest::Part(len.saturating_sub(n), len),
        (true, _, _) => RangeRequest::Unsatisfiable,
        (false, Some(start), _) if start >= len => RangeRequest::Unsatisfiable,
        (false, Some(start), None) if last.trim().is_empty() => RangeRequest::Part(start, len),
        (false, Some(start), Some(end)) if end >= start => {
            RangeRequest::Part(start, end.saturating_add(1).min(len))
        }
        _ => RangeRequest::Whole,
    }
}

/// The path a request names, as a key of the table (`/` is the page); queries are ignored.
fn table_key(target: &str) -> String {
    let path = target.split(['?', '#']).next().unwrap_or("");
    match path.strip_prefix('/') {
        Some("") | None => "index.html".into(),
        Some(rest) => rest.to_string(),
    }
}

/// The content type of a served path.
fn content_type(path: &str) -> &'static str {
    match path.rsplit('.').next() {
        Some("html") => "text/html; charset=utf-8",
        Some("js") => "text/javascript; charset=utf-8",
        Some("json") => "application/json",
        Some("glb") => "model/gltf-binary",
        Some("md") | Some("txt") => "text/plain; charset=utf-8",
        _ => "application/octet-stream",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn site(address: &str) -> Site {
        let mut files = BTreeMap::new();
        files.insert("index.html".to_string(), b"<html>".to_vec());
        files.insert("avatar.glb".to_string(), (0..100u8).collect());
        Site::new(files, address.parse().unwrap())
    }

    fn get(site: &Site, request: &str) -> (u16, Vec<(&'static str, String)>, Vec<u8>) {
        let r = answer(site, request.as_bytes());
        (r.status, r.headers, r.body.to_vec())
    }

    fn header(headers: &[(&'static str, String)], name: &str) -> Option<String> {
        headers
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, v)| v.clone())
    }

    #[test]
    fn only_get_and_head_of_paths_in_the_table() {
        let s = site("127.0.0.1:8080");
        let (status, _, body) = get(&s, "GET / HTTP/1.1\r\nHost: 127.0.0.1:8080");
        assert_eq!((status, body.as_slice()), (200, b"<html>".as_slice()));
        let (status, headers, body) = get(&s, "HEAD /avatar.glb HTTP/1.1\r\nHost: localhost:8080");
        assert_eq!(status, 200);
        assert!(body.is_empty());
        assert_eq!(header(&headers, "Content-Length").as_deref(), Some("100"));
        for method in ["POST", "DELETE", "TRACE", "CONNECT", "OPTIONS", "PUT"] {
            let (status, headers, _) = get(&s, &format!("{method} / HTTP/1.1\r\nHost: localhost"));
            assert_eq!(status, 405, "{method}");
            assert_eq!(header(&headers, "Allow").as_deref(), Some("GET, HEAD"));
        }
        // A target that is not a path (absolute form, asterisk, bare name) does not serve the
        // page.
        for target in ["index.html", "*", "http://evil.example/", "avatar.glb"] {
            let (status, _, _) = get(&s, &format!("GET {target} HTTP/1.1\r\nHost: localhost"));
            assert_eq!(status, 400, "{target}");
        }
        for target in [
            "/../Cargo.toml",
            "/%2e%2e/x",
            "/etc/passwd",
            "/vendor/../index.html",
        ] {
            let (status, _, _) = get(&s, &format!("GET {target} HTTP/1.1\r\nHost: localhost"));
            assert_eq!(status, 404, "{target}");
        }
        assert_eq!(get(&s, "GET / HTTP/1.1\r\nbroken").0, 400);
        assert_eq!(get(&s, "GET / SPDY/3\r\nHost: localhost").0, 400);
        assert_eq!(get(&s, "GET  / HTTP/1.1\r\nHost: localhost").0, 400);
    }

    #[test]
    fn the_host_header_must_name_this_server() {
        let s = site("127.0.0.1:8080");
        for host in [
            "127.0.0.1",
            "127.0.0.1:8080",
            "localhost",
            "LOCALHOST:8080",
            "[::1]:8080",
        ] {
            let (status, _, _) = get(&s, &format!("GET / HTTP/1.1\r\nHost: {host}"));
            assert_eq!(status, 200, "{host}");
        }
        // A rebinding page's name, another port, another address, none, or two.
        for host in [
            "Host: evil.example",
            "Host: evil.example:8080",
            "Host: 127.0.0.1:9999",
            "Host: 192.168.1.20",
            "Host: localhost.evil.example",
            "X: y",
        ] {
            let (status, _, _) = get(&s, &format!("GET / HTTP/1.1\r\n{host}"));
            assert_eq!(status, 421, "{host}");
        }
        // Two Host headers: a malformed request (RFC 9112: 400).
        assert_eq!(
            get(
                &s,
                "GET / HTTP/1.1\r\nHost: localhost\r\nHost: evil.example"
            )
            .0,
            400
        );
        // Listening on a LAN address or on all of them: clients name it by its IP address.
        let lan = site("192.168.1.20:8080");
        assert_eq!(
            get(&lan, "GET / HTTP/1.1\r\nHost: 192.168.1.20:8080").0,
            200
        );
        assert_eq!(get(&lan, "GET / HTTP/1.1\r\nHost: 10.0.0.1:8080").0, 421);
        let all = site("0.0.0.0:8080");
        assert_eq!(get(&all, "GET / HTTP/1.1\r\nHost: 10.0.0.1:8080").0, 200);
        assert_eq!(
            get(&all, "GET / HTTP/1.1\r\nHost: evil.example:8080").0,
            421
        );
    }

    #[test]
    fn ranges_answer_parts() {
        let s = site("127.0.0.1:8080");
        let request = |range: &str| {
            get(
                &s,
                &format!("GET /avatar.glb HTTP/1.1\r\nHost: localhost\r\nRange: {range}"),
            )
        };
        let (status, headers, body) = request("bytes=10-19");
        assert_eq!(status, 206);
        assert_eq!(body, (10..20u8).collect::<Vec<_>>());
        assert_eq!(
            header(&headers, "Content-Range").as_deref(),
            Some("bytes 10-19/100")
        );
        assert_eq!(header(&headers, "Content-Length").as_deref(), Some("10"));
        assert_eq!(request("bytes=95-").2, (95..100u8).collect::<Vec<_>>());
        assert_eq!(request("bytes=-3").2, vec![97, 98, 99]);
        assert_eq!(request("bytes=90-1000").2, (90..100u8).collect::<Vec<_>>());
        let (status, headers, _) = request("bytes=100-");
        assert_eq!(status, 416);
        assert_eq!(
            header(&headers, "Content-Range").as_deref(),
            Some("bytes */100")
        );
        assert_eq!(request("bytes=-0").0, 416);
        // Several ranges, another unit, nonsense: the whole file.
        for range in ["bytes=0-1,5-6", "items=0-1", "bytes=5-2", "bytes=x-y"] {
            let (status, _, body) = request(range);
            assert_eq!((status, body.len()), (200, 100), "{range}");
        }
    }

    /// The server under load on the loopback address: stalled readers, trickled heads and
    /// bodies that never come hold their own connections only; 200 concurrent requests are all
    /// answered, each within a second. Bounded: a few seconds, every socket closed at the end.
    #[test]
    fn stalled_clients_do_not_hold_the_others() {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let address = listener.local_addr().unwrap();
        let mut files = BTreeMap::new();
        files.insert("index.html".to_string(), b"<html>".to_vec());
        // Larger than the socket buffers, so a client that does not read stalls the write.
        files.insert("avatar.glb".to_string(), vec![7u8; 64 << 20]);
        let site = Site::new(files, address);
        std::thread::spawn(move || serve(listener, site));

        let send = |text: &str| {
            let mut s = TcpStream::connect(address).unwrap();
            s.write_all(text.as_bytes()).unwrap();
            s
        };
        let host = format!("Host: {address}");
        // Held open until the end of the test.
        let mut held = Vec::new();
        for _ in 0..8 {
            held.push(send(&format!("GET /avatar.glb HTTP/1.1\r\n{host}\r\n\r\n")));
            held.push(send(&format!(
                "POST / HTTP/1.1\r\n{host}\r\nContent-Length: 1000000\r\n\r\nabc"
            )));
            held.push(send("GET / HTTP/1.1\r\nHo"));
        }
        std::thread::sleep(Duration::from_millis(200));

        let clients: Vec<_> = (0..200)
            .map(|_| {
                let host = host.clone();
                std::thread::spawn(move || {
                    let started = Instant::now();
                    let mut s = TcpStream::connect(address).unwrap();
                    // Long enough to see an answer that waited for a stalled client to time out.
                    s.set_read_timeout(Some(HEAD_DEADLINE + WRITE_TIMEOUT))
                        .unwrap();
                    s.write_all(format!("GET / HTTP/1.1\r\n{host}\r\n\r\n").as_bytes())
                        .unwrap();
                    let mut answer = String::new();
                    s.read_to_string(&mut answer).unwrap();
                    (started.elapsed(), answer)
                })
            })
            .collect();
        for client in clients {
            let (took, answer) = client.join().unwrap();
            assert!(answer.starts_with("HTTP/1.1 200 OK"), "{answer}");
            assert!(answer.ends_with("<html>"), "{answer}");
            // A server that let the stalled clients hold it would answer only once their
            // deadlines ran out; the margin keeps a loaded CI machine (1.06 s seen) from failing.
            assert!(took < HEAD_DEADLINE / 2, "answered after {took:?}");
        }
        drop(held);
    }
}
