//! Several `canopy-server serve` replicas on one PostgreSQL database and one data folder
//! (issue 24): scenes, edits and files made through one are served by the other; edits through
//! both lose nothing and make no version twice; a viewer on one hears of edits and deletions made
//! through the other, and sees the other's viewers; `kill -9` of one loses no acknowledged edit; a
//! replica that cannot reach the database serves assets, answers 503 and recovers by itself. The
//! replicas start on what a bake job (`serve --publish-only`) published: neither bakes.
//!
//! Needs `CANOPY_TEST_POSTGRES=postgres://USER@HOST:PORT/DB` (`.ci/run` starts a throwaway
//! cluster) and `psql`; skipped without the variable, except under CI, where it fails.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use canopy_e2e::net::{Server, WsClient, free_port, http};
use canopy_e2e::scratch;
use serde_json::{Value, json};

/// A fresh database for test `name`, as a URL; `None` (skipped) without a server outside CI.
fn fresh_database(name: &str) -> Option<String> {
    let Ok(url) = std::env::var("CANOPY_TEST_POSTGRES") else {
        assert!(
            std::env::var_os("CI").is_none(),
            "CANOPY_TEST_POSTGRES is not set: CI must run the replica tests (.ci/run starts PostgreSQL)"
        );
        eprintln!("skipped: CANOPY_TEST_POSTGRES is not set");
        return None;
    };
    let db = format!("canopy_e2e_{name}");
    for sql in [
        format!("DROP DATABASE IF EXISTS {db} WITH (FORCE)"),
        format!("CREATE DATABASE {db}"),
    ] {
        let out = Command::new("psql")
            .args([url.as_str(), "-v", "ON_ERROR_STOP=1", "-qc", &sql])
            .output()
            .expect("psql");
        assert!(out.status.success(), "psql: {}", String::from_utf8_lossy(&out.stderr));
    }
    let (base, _) = url
        .rsplit_once('/')
        .expect("CANOPY_TEST_POSTGRES is postgres://USER@HOST:PORT/DB");
    Some(format!("{base}/{db}"))
}

/// Two replicas on one data folder and database, both started on data a bake job published (the
/// demo of two synthetic models), neither baking.
fn replicas(name: &str, url: &str) -> (Server, Server) {
    let data = scratch(name).join("data");
    let job = Command::new(canopy_e2e::server())
        .args(["serve", "--publish-only", "--demo-synthetic", "2", "--demo-trees", "50"])
        .arg("--data")
        .arg(&data)
        .args(["--database", url])
        .output()
        .expect("run the bake job");
    assert!(
        job.status.success(),
        "bake job: {}",
        String::from_utf8_lossy(&job.stderr)
    );
    assert!(String::from_utf8_lossy(&job.stdout).contains("canopy-server published into"));
    let args = [
        "--no-demo",
        "--database",
        url,
        "--open-creation",
        "--edits-per-s",
        "1000",
    ];
    (Server::start(&data, &args), Server::start(&data, &args))
}

fn post(addr: SocketAddr, path: &str, token: Option<&str>, body: &Value) -> canopy_e2e::net::HttpResponse {
    let auth = token.map(|t| format!("Bearer {t}"));
    let headers: Vec<(&str, &str)> = auth.iter().map(|a| ("Authorization", a.as_str())).collect();
    http(addr, "POST", path, &headers, Some(body.to_string().as_bytes()))
}

fn create(addr: SocketAddr, id: &str) -> String {
    let r = post(
        addr,
        "/api/scenes",
        None,
        &json!({"name": id, "id": id, "bounds": {"min": [0, 0], "max": [100, 100]}}),
    );
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    r.json()["write_token"].as_str().expect("token").to_string()
}

fn add(addr: SocketAddr, id: &str, token: &str, x: f64) -> Result<u64, u16> {
    let r = post(
        addr,
        &format!("/api/scenes/{id}/instances"),
        Some(token),
        &json!({"add": [{"model": "synthetic-0", "position": [x, 0.0, 5.0]}]}),
    );
    if r.status == 200 {
        Ok(r.json()["added_ids"][0].as_u64().expect("id"))
    } else {
        Err(r.status)
    }
}

fn ids(addr: SocketAddr, id: &str) -> Vec<u64> {
    let r = http(addr, "GET", &format!("/api/scenes/{id}/instances"), &[], None);
    assert_eq!(r.status, 200);
    r.json()["instances"]
        .as_array()
        .expect("list")
        .iter()
        .map(|i| i["id"].as_u64().expect("id"))
        .collect()
}

#[test]
fn two_replicas_serve_each_others_scenes_edits_and_files() {
    let Some(url) = fresh_database("share") else { return };
    let (a, b) = replicas("replicas-share", &url);
    // The demo A made is B's too.
    assert_eq!(http(b.addr, "GET", "/api/scenes/demo", &[], None).status, 200);
    let token = create(a.addr, "shared");
    // Four writers, two through each replica.
    let acked = Arc::new(Mutex::new(Vec::new()));
    let writers: Vec<_> = (0..4)
        .map(|k| {
            let (addr, token, acked) = (if k % 2 == 0 { a.addr } else { b.addr }, token.clone(), acked.clone());
            std::thread::spawn(move || {
                for n in 0..10 {
                    let id = add(addr, "shared", &token, f64::from(k * 20 + n)).expect("edit acknowledged");
                    acked.lock().expect("acked").push(id);
                }
            })
        })
        .collect();
    for w in writers {
        w.join().expect("writer");
    }
    let mut acked = acked.lock().expect("acked").clone();
    acked.sort_unstable();
    assert_eq!(
        acked,
        (1..=40).collect::<Vec<u64>>(),
        "every edit acknowledged once, ids unique"
    );
    let versions: Vec<u64> = http(b.addr, "GET", "/api/scenes/shared/versions", &[], None).json()["versions"]
        .as_array()
        .expect("versions")
        .iter()
        .map(|v| v["version"].as_u64().expect("version"))
        .collect();
    assert_eq!(versions.last(), Some(&41), "one version per edit: {versions:?}");
    // Both replicas answer the same manifest, and serve its pack (written by either) byte for byte.
    let (ma, mb) = (
        http(a.addr, "GET", "/api/scenes/shared/manifest", &[], None),
        http(b.addr, "GET", "/api/scenes/shared/manifest", &[], None),
    );
    assert_eq!(ma.body, mb.body);
    let pack = ma.json()["pack"]["url"].as_str().expect("pack url").to_string();
    let (pa, pb) = (
        http(a.addr, "GET", &pack, &[], None),
        http(b.addr, "GET", &pack, &[], None),
    );
    assert_eq!((pa.status, pb.status), (200, 200));
    assert_eq!(pa.body, pb.body);
    assert_eq!(ids(a.addr, "shared"), acked);
    // An edit through B is in A's manifest at once, and A's live viewers hear of it (LISTEN/NOTIFY).
    let mut viewer = WsClient::connect(a.addr, "/api/scenes/shared/live").expect("upgrade");
    viewer.recv_until(5, |m| m["type"] == "welcome");
    let t0 = Instant::now();
    add(b.addr, "shared", &token, 99.0).expect("edit");
    assert_eq!(
        http(a.addr, "GET", "/api/scenes/shared", &[], None).json()["version"],
        42
    );
    let heard = viewer.recv_until(50, |m| m["type"] == "version");
    assert_eq!(heard["version"], 42);
    assert!(t0.elapsed() < Duration::from_secs(1), "heard after {:?}", t0.elapsed());
    // And of a deletion through B.
    let auth = format!("Bearer {token}");
    let r = http(
        b.addr,
        "DELETE",
        "/api/scenes/shared",
        &[("Authorization", &auth)],
        None,
    );
    assert_eq!(r.status, 204);
    viewer.recv_until(50, |m| m["type"] == "deleted");
}

#[test]
fn kill_9_of_a_replica_loses_no_acknowledged_edit_and_the_other_keeps_serving() {
    let Some(url) = fresh_database("kill") else { return };
    let (a, b) = replicas("replicas-kill", &url);
    let token = create(b.addr, "kept");
    let stop = Arc::new(AtomicBool::new(false));
    let acked = Arc::new(Mutex::new(Vec::new()));
    let writer = {
        let (addr, token, stop, acked) = (a.addr, token.clone(), stop.clone(), acked.clone());
        std::thread::spawn(move || {
            let mut n = 0;
            while !stop.load(Ordering::SeqCst) {
                // Refused or cut off once A is gone (the helper panics): only acknowledged edits
                // count.
                match std::panic::catch_unwind(|| add(addr, "kept", &token, f64::from(n % 90))) {
                    Ok(Ok(id)) => acked.lock().expect("acked").push(id),
                    Ok(Err(_)) => {}
                    Err(_) => break,
                }
                n += 1;
            }
        })
    };
    let t0 = Instant::now();
    while acked.lock().expect("acked").len() < 15 && t0.elapsed() < Duration::from_mins(1) {
        std::thread::sleep(Duration::from_millis(5));
    }
    let status = Command::new("kill")
        .args(["-KILL", &a.pid().to_string()])
        .status()
        .expect("kill");
    assert!(status.success());
    std::thread::sleep(Duration::from_millis(300));
    stop.store(true, Ordering::SeqCst);
    writer.join().expect("writer");
    let acked = acked.lock().expect("acked").clone();
    assert!(acked.len() >= 15, "{} edits acknowledged before the kill", acked.len());
    // B serves every acknowledged edit and takes more.
    let kept = ids(b.addr, "kept");
    for id in &acked {
        assert!(kept.contains(id), "acknowledged instance {id} lost");
    }
    add(b.addr, "kept", &token, 1.0).expect("B keeps taking edits");
    assert_eq!(http(b.addr, "GET", "/healthz", &[], None).status, 200);
    drop(a);
}

fn send_pose(v: &mut WsClient, x: f32) {
    v.send_text(&json!({"type": "pose", "position": [x, 2.0, 3.0], "orientation": [0.0, 0.0, 0.0, 1.0]}).to_string());
}

#[test]
fn viewers_on_two_replicas_see_each_other_and_a_killed_replicas_viewers_leave() {
    let Some(url) = fresh_database("presence") else { return };
    let (a, b) = replicas("replicas-presence", &url);
    let live = "/api/scenes/demo/live";
    let welcome_lists = |addr: SocketAddr, id: u64| {
        let mut probe = WsClient::connect(addr, live).expect("upgrade");
        let welcome = probe.recv_until(5, |m| m["type"] == "welcome");
        welcome["viewers"]
            .as_array()
            .expect("viewers")
            .iter()
            .any(|v| v["viewer"] == id)
    };
    // A viewer alone on A: B, with no viewer of its own, still keeps it (the relay makes B's
    // hub), so B's first viewer finds it in its welcome...
    let mut first = WsClient::connect(a.addr, live).expect("upgrade on A");
    let id_first = first.recv_until(5, |m| m["type"] == "welcome")["viewer"]
        .as_u64()
        .expect("id");
    std::thread::sleep(Duration::from_secs(1));
    assert!(welcome_lists(b.addr, id_first), "B's welcome lacks A's lone viewer");
    // ...and forgets it when it leaves, though it was A's last (not 5 s later, when unheard of).
    std::thread::sleep(Duration::from_secs(1));
    drop(first);
    std::thread::sleep(Duration::from_secs(1));
    assert!(!welcome_lists(b.addr, id_first), "B still lists A's viewer that left");
    let mut vb = WsClient::connect(b.addr, live).expect("upgrade on B");
    let id_b = vb.recv_until(5, |m| m["type"] == "welcome")["viewer"]
        .as_u64()
        .expect("id");
    let mut va = WsClient::connect(a.addr, live).expect("upgrade on A");
    let id_a = va.recv_until(5, |m| m["type"] == "welcome")["viewer"]
        .as_u64()
        .expect("id");
    assert_ne!(id_a, id_b, "viewer ids are unique across replicas");
    // A's viewer moves: B's viewer is told of it (join, then its pose) within a second.
    let t0 = Instant::now();
    send_pose(&mut va, 7.5);
    let seen = vb.recv_until(10, |m| m["type"] == "presence");
    assert_eq!(seen["viewer"], id_a);
    assert_eq!(seen["pose"]["position"], json!([7.5, 2.0, 3.0]));
    assert!(
        t0.elapsed() < Duration::from_secs(1),
        "A's pose on B after {:?}",
        t0.elapsed()
    );
    // And the other way round.
    send_pose(&mut vb, -4.0);
    let seen = va.recv_until(10, |m| m["type"] == "presence" && m["viewer"] == id_b);
    assert_eq!(seen["pose"]["position"], json!([-4.0, 2.0, 3.0]));
    // A viewer joining B now finds A's viewer, with its pose, in its welcome.
    let mut late = WsClient::connect(b.addr, live).expect("upgrade on B");
    let welcome = late.recv_until(5, |m| m["type"] == "welcome");
    let listed = welcome["viewers"].as_array().expect("viewers");
    assert!(
        listed
            .iter()
            .any(|v| v["viewer"] == id_a && v["pose"]["position"] == json!([7.5, 2.0, 3.0])),
        "{welcome}"
    );
    drop(late);
    // A's viewer closes: B's viewer hears it left within a second.
    let t0 = Instant::now();
    drop(va);
    vb.recv_until(20, |m| m["type"] == "leave" && m["viewer"] == id_a);
    assert!(
        t0.elapsed() < Duration::from_secs(1),
        "leave on B after {:?}",
        t0.elapsed()
    );
    // A replica killed with its viewers: they leave B's scene once their rosters stop (5 s).
    let mut doomed = WsClient::connect(a.addr, live).expect("upgrade on A");
    let id_doomed = doomed.recv_until(5, |m| m["type"] == "welcome")["viewer"]
        .as_u64()
        .expect("id");
    vb.recv_until(20, |m| m["type"] == "join" && m["viewer"] == id_doomed);
    let t0 = Instant::now();
    let status = Command::new("kill")
        .args(["-KILL", &a.pid().to_string()])
        .status()
        .expect("kill");
    assert!(status.success());
    vb.recv_until(50, |m| m["type"] == "leave" && m["viewer"] == id_doomed);
    let gone = t0.elapsed();
    assert!(
        gone < Duration::from_secs(8),
        "killed replica's viewer left B after {gone:?}"
    );
    drop((doomed, a));
}

/// Forwards connections from `listener` to `to` while `open`; drops them all when it turns false.
fn forward(listener: TcpListener, to: SocketAddr, open: Arc<AtomicBool>) {
    listener.set_nonblocking(true).expect("nonblocking");
    std::thread::spawn(move || {
        let mut pairs: Vec<TcpStream> = Vec::new();
        loop {
            if !open.load(Ordering::SeqCst) {
                for s in pairs.drain(..) {
                    let _ = s.shutdown(std::net::Shutdown::Both);
                }
            }
            match listener.accept() {
                Ok((client, _)) if open.load(Ordering::SeqCst) => {
                    let Ok(server) = TcpStream::connect(to) else { continue };
                    for (mut from, mut into) in [
                        (client.try_clone().expect("clone"), server.try_clone().expect("clone")),
                        (server.try_clone().expect("clone"), client.try_clone().expect("clone")),
                    ] {
                        std::thread::spawn(move || {
                            let mut buf = [0u8; 16384];
                            while let Ok(n) = from.read(&mut buf) {
                                if n == 0 || into.write_all(&buf[..n]).is_err() {
                                    break;
                                }
                            }
                            let _ = into.shutdown(std::net::Shutdown::Write);
                        });
                    }
                    pairs.extend([client, server]);
                }
                Ok(_) => {}
                Err(_) => std::thread::sleep(Duration::from_millis(10)),
            }
        }
    });
}

fn wait_for(addr: SocketAddr, path: &str, status: u16) -> u16 {
    let t0 = Instant::now();
    loop {
        let got = http(addr, "GET", path, &[], None).status;
        if got == status || t0.elapsed() > Duration::from_secs(15) {
            return got;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn a_replica_without_its_database_serves_assets_answers_503_and_recovers() {
    let Some(url) = fresh_database("down") else { return };
    // The replica reaches PostgreSQL through a forwarder this test opens and closes.
    let real: SocketAddr = {
        let host_port = url
            .split('@')
            .nth(1)
            .and_then(|r| r.split('/').next())
            .expect("HOST:PORT in the URL");
        std::net::ToSocketAddrs::to_socket_addrs(host_port)
            .expect("address")
            .next()
            .expect("address")
    };
    let port = free_port();
    let via = url.replacen(&real.port().to_string(), &port.to_string(), 1);
    let (a, _) = replicas("replicas-down-a", &url);
    let data = a.data.clone();
    let b = Server::start(&data, &["--no-demo", "--database", &via]);
    assert_eq!(http(b.addr, "GET", "/healthz", &[], None).status, 503);
    assert_eq!(http(b.addr, "GET", "/api/scenes", &[], None).status, 503);
    let r = http(b.addr, "GET", "/api/scenes/demo", &[], None);
    assert_eq!(r.status, 503);
    assert_eq!(r.header("retry-after"), Some("1"));
    assert!(r.json()["error"].as_str().is_some_and(|e| e.contains("unavailable")));
    // Assets are still served: the demo's tree files.
    let manifest = http(a.addr, "GET", "/api/scenes/demo/manifest", &[], None).json();
    let model = manifest["models"][0]["url"].as_str().expect("model url").to_string();
    assert_eq!(http(b.addr, "GET", &model, &[], None).status, 200);
    // The database comes up: B recovers by itself.
    let open = Arc::new(AtomicBool::new(true));
    forward(
        TcpListener::bind(("127.0.0.1", port)).expect("bind"),
        real,
        open.clone(),
    );
    assert_eq!(
        wait_for(b.addr, "/healthz", 200),
        200,
        "healthy once the database is back"
    );
    assert_eq!(http(b.addr, "GET", "/api/scenes/demo", &[], None).status, 200);
    // A viewer on B watches a scene A edits.
    let token = create(a.addr, "cut");
    let mut viewer = WsClient::connect(b.addr, "/api/scenes/cut/live").expect("upgrade on B");
    assert_eq!(viewer.recv_until(5, |m| m["type"] == "welcome")["version"], 1);
    // And goes: 503 again (noticed without traffic to the API), then back.
    open.store(false, Ordering::SeqCst);
    assert_eq!(
        wait_for(b.addr, "/healthz", 503),
        503,
        "unhealthy once the database is gone"
    );
    assert_eq!(http(b.addr, "GET", "/api/scenes/demo", &[], None).status, 503);
    // An edit B cannot hear of: its notification goes out while B's listener is cut off.
    add(a.addr, "cut", &token, 10.0).expect("edit through A");
    open.store(true, Ordering::SeqCst);
    assert_eq!(wait_for(b.addr, "/healthz", 200), 200);
    assert_eq!(http(b.addr, "GET", "/api/scenes/demo", &[], None).status, 200);
    // Listening again, B reads what it missed and tells its viewer.
    let t0 = Instant::now();
    let told = viewer.recv_until(50, |m| m["type"] == "version");
    assert_eq!(told["version"], 2);
    assert!(
        t0.elapsed() < Duration::from_secs(5),
        "missed version told {:?} after recovery",
        t0.elapsed()
    );
}
