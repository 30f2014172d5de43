//! The serving core's fault kinds, each reproduced against a real server on loopback (issue 14):
//! one bad request never fails another, refusals cost nothing, connections cannot pile up, and
//! the listener keeps answering while in-flight work drains.

mod server_common;

use std::time::{Duration, Instant};

use serde_json::json;
use server_common::*;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Reads from `stream` until the peer closes it or `limit` passes; returns what arrived and
/// whether it was closed.
async fn read_until_closed(stream: &mut TcpStream, limit: Duration) -> (String, bool) {
    let mut out = Vec::new();
    let mut buf = [0u8; 4096];
    let deadline = Instant::now() + limit;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match tokio::time::timeout(left, stream.read(&mut buf)).await {
            Ok(Ok(0)) | Ok(Err(_)) => return (String::from_utf8_lossy(&out).into_owned(), true),
            Ok(Ok(n)) => out.extend_from_slice(&buf[..n]),
            Err(_) => return (String::from_utf8_lossy(&out).into_owned(), false),
        }
    }
}

/// Starts a localize whose JSON body is sent slowly; returns the socket and the unsent rest.
async fn start_trickled_localize(server: &TestServer, body: &[u8], sent: usize) -> TcpStream {
    let mut stream = TcpStream::connect(server.addr()).await.unwrap();
    let head = format!(
        "POST /v1/maps/street/localize HTTP/1.1\r\nhost: test\r\ncontent-type: application/json\r\ncontent-length: {}\r\n\r\n",
        body.len()
    );
    stream.write_all(head.as_bytes()).await.unwrap();
    stream.write_all(&body[..sent]).await.unwrap();
    stream
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_absurd_prior_fails_alone_and_its_batch_mates_succeed() {
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &["--max-batch", "32"]).await;
    let mut absurd = kitti_request(3);
    absurd["prior_camera_from_map"] = json!([[1, 0, 0, 3e38], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]);
    let mut tasks = Vec::new();
    for i in 0..8 {
        let body = if i == 3 { absurd.clone() } else { kitti_request(3) };
        let (client, url) = (server.client.clone(), server.url("/v1/maps/street/localize"));
        tasks.push(tokio::spawn(async move {
            let r = client.post(url).json(&body).send().await.unwrap();
            (r.status().as_u16(), r.json::<serde_json::Value>().await.unwrap())
        }));
    }
    for (i, task) in tasks.into_iter().enumerate() {
        let (status, body) = task.await.unwrap();
        if i == 3 {
            assert_eq!((status, body["error_type"].as_str()), (422, Some("invalid_input")), "{body}");
            assert!(body["error"].as_str().unwrap().contains("prior_camera_from_map"), "{body}");
        } else {
            assert_eq!(status, 200, "request {i}: {body}");
        }
    }
    server.stop().await;
}

/// A full server refuses with 429 before reading the body: the refused client has sent only its
/// headers when the answer arrives.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refused_request_is_refused_before_its_body_is_read() {
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &["--queue-capacity", "1"]).await;
    // The one slot is held by a request whose body is still arriving.
    let body = serde_json::to_vec(&kitti_request(1)).unwrap();
    let mut holder = start_trickled_localize(&server, &body, 100).await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(server.state.scheduler.queue_depth(), 1);

    let mut refused = TcpStream::connect(server.addr()).await.unwrap();
    let head = "POST /v1/maps/street/localize HTTP/1.1\r\nhost: test\r\ncontent-type: application/json\r\ncontent-length: 15000000\r\n\r\n";
    refused.write_all(head.as_bytes()).await.unwrap();
    let started = Instant::now();
    let (answer, _) = read_until_closed(&mut refused, Duration::from_secs(2)).await;
    assert!(answer.starts_with("HTTP/1.1 429"), "{answer}");
    assert!(answer.contains("queue_full") && answer.to_ascii_lowercase().contains("retry-after"), "{answer}");
    assert!(started.elapsed() < Duration::from_secs(2), "answered without waiting for 15 MB");

    // The holder finishes its body and is localized.
    holder.write_all(&body[100..]).await.unwrap();
    let (answer, _) = read_until_closed(&mut holder, Duration::from_secs(20)).await;
    assert!(answer.starts_with("HTTP/1.1 200"), "{}", &answer[..answer.len().min(300)]);
    server.stop().await;
}

/// Headers must arrive within the header timeout, and an idle kept-alive connection is closed
/// after it; connections over the limit wait until one closes instead of exhausting descriptors.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_headers_and_idle_connections_are_cut() {
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &["--header-timeout-s", "1", "--max-connections", "3"]).await;

    let mut trickler = TcpStream::connect(server.addr()).await.unwrap();
    trickler.write_all(b"GET /health HTTP/1.1\r\nhost: te").await.unwrap();
    let started = Instant::now();
    let (_, closed) = read_until_closed(&mut trickler, Duration::from_secs(5)).await;
    assert!(closed, "a connection whose headers never finish is closed");
    assert!(started.elapsed() < Duration::from_secs(4), "{:?}", started.elapsed());

    let mut idle = TcpStream::connect(server.addr()).await.unwrap();
    idle.write_all(b"GET /health HTTP/1.1\r\nhost: test\r\n\r\n").await.unwrap();
    let (answer, closed) = read_until_closed(&mut idle, Duration::from_secs(5)).await;
    assert!(answer.starts_with("HTTP/1.1 200") && closed, "answered, then closed when idle: {answer}");

    // Three silent sockets fill the connection limit; /health still answers once they are cut.
    let mut silent = Vec::new();
    for _ in 0..3 {
        silent.push(TcpStream::connect(server.addr()).await.unwrap());
    }
    let started = Instant::now();
    let r = tokio::time::timeout(Duration::from_secs(8), server.client.get(server.url("/health")).send()).await;
    assert_eq!(r.expect("answered after the idle sockets were cut").unwrap().status(), 200);
    assert!(started.elapsed() >= Duration::from_millis(500), "it had to wait for a free connection");
    server.stop().await;
}

/// The probe port (`--probe-port`) answers /health and /ready within a second while the main
/// port's connection limit is held full by silent and trickling clients (more of them waiting in
/// its backlog), which starve a probe on the main port; it serves nothing else.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn probes_answer_while_the_connection_limit_is_full() {
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &["--max-connections", "4", "--header-timeout-s", "30"]).await;
    let mut held = Vec::new();
    for i in 0..24 {
        let mut stream = TcpStream::connect(server.addr()).await.unwrap();
        if i % 2 == 1 {
            stream.write_all(b"GET /health HTTP/1.1\r\nhost: t").await.unwrap(); // trickling: headers never finish
        }
        held.push(stream);
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    // A client without pooled connections: each request opens its own, as a kubelet probe does.
    let fresh = reqwest::Client::builder().pool_max_idle_per_host(0).build().unwrap();
    let starved = tokio::time::timeout(Duration::from_secs(1), fresh.get(server.url("/health")).send()).await;
    assert!(starved.is_err(), "the main port's limit is full: its /health waits");
    for path in ["/health", "/ready", "/health", "/ready"] {
        let started = Instant::now();
        let r = tokio::time::timeout(Duration::from_secs(1), fresh.get(format!("{}{path}", server.probe_base)).send()).await;
        let r = r.unwrap_or_else(|_| panic!("the probe port's {path} answers within 1 s")).unwrap();
        assert_eq!(r.status(), 200, "{path}");
        println!("probe port {path} with the main port full: {:.1} ms", started.elapsed().as_secs_f64() * 1000.0);
    }
    let ready: serde_json::Value = fresh.get(format!("{}/ready", server.probe_base)).send().await.unwrap().json().await.unwrap();
    assert_eq!(ready["ready"], true);
    let metrics = fresh.get(format!("{}/metrics", server.probe_base)).send().await.unwrap();
    assert_eq!(metrics.status(), 200);
    let other = fresh.get(format!("{}/v1/maps", server.probe_base)).send().await.unwrap();
    assert_eq!(other.status(), 404, "the probe port serves the probes only");
    assert_eq!(other.json::<serde_json::Value>().await.unwrap()["error_type"], "not_found");
    drop(held);
    server.stop().await;
}

/// On shutdown the listener keeps answering (/ready 503, new localizations 503 `draining`, with
/// `connection: close`) until the in-flight localization has finished; then the server stops.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn draining_keeps_answering_until_in_flight_work_is_done() {
    let maps = maps_dir_with_street();
    let mut server = TestServer::start(&tiny_model(), maps.path(), &["--shutdown-grace-s", "20"]).await;
    let body = serde_json::to_vec(&kitti_request(2)).unwrap();
    let mut in_flight = start_trickled_localize(&server, &body, 64).await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(server.state.lifecycle.in_flight(), 1);

    server.signal_shutdown();
    tokio::time::sleep(Duration::from_millis(200)).await;
    let r = server.client.get(server.url("/ready")).send().await.expect("the listener still answers");
    assert_eq!(r.status(), 503);
    assert_eq!(r.headers().get("connection").map(|v| v.to_str().unwrap()), Some("close"));
    let (status, json, _) = server.localize("street", &kitti_request(1)).await;
    assert_eq!((status, json["error_type"].as_str()), (503, Some("draining")), "{json}");

    in_flight.write_all(&body[64..]).await.unwrap();
    let (answer, _) = read_until_closed(&mut in_flight, Duration::from_secs(20)).await;
    assert!(answer.starts_with("HTTP/1.1 200"), "the in-flight request completes: {}", &answer[..answer.len().min(300)]);
    let addr = server.addr();
    server.stop().await;
    assert!(TcpStream::connect(addr).await.is_err(), "the listener is closed after the drain");
}

/// A map id that is not valid percent-encoded UTF-8 gets the API's JSON error, not plain text.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_undecodable_path_segment_is_a_json_400() {
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &[]).await;
    for path in ["/v1/maps/%FF%FE", "/v1/maps/%FF/localize"] {
        let r = if path.ends_with("localize") {
            server.client.post(server.url(path)).json(&kitti_request(1)).send().await.unwrap()
        } else {
            server.client.get(server.url(path)).send().await.unwrap()
        };
        assert_eq!(r.status(), 400, "{path}");
        assert!(r.headers()["content-type"].to_str().unwrap().starts_with("application/json"), "{path}");
        assert_eq!(r.json::<serde_json::Value>().await.unwrap()["error_type"], "bad_request");
    }
    server.stop().await;
}
