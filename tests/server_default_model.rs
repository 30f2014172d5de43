//! The server with the project's default model (`models/`): a localization, and overload
//! answered fast with 429 instead of piling up.

mod common;

use std::time::{Duration, Instant};

use common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn default_model_localizes_and_overload_gets_429() {
    let maps = maps_dir_with_street();
    let server = TestServer::start(
        &default_model(),
        maps.path(),
        &["--workers", "1", "--max-batch", "1", "--queue-capacity", "1"],
    )
    .await;

    let (status, body, _) = server.localize("street", &kitti_request(3)).await;
    assert_eq!(status, 200, "{body}");
    assert!(body["iterations"].as_u64().unwrap() >= 1);

    // Twelve requests at once against one worker with room for one waiting request: the
    // overflow is refused at once with 429 + Retry-After, and everything else succeeds.
    let request = kitti_request(10);
    let started = Instant::now();
    let mut tasks = Vec::new();
    for _ in 0..12 {
        let client = server.client.clone();
        let url = server.url("/v1/maps/street/localize");
        let request = request.clone();
        tasks.push(tokio::spawn(async move {
            let t = Instant::now();
            let r = client.post(url).json(&request).send().await.unwrap();
            let status = r.status().as_u16();
            let retry_after = r.headers().get("retry-after").is_some();
            let body: serde_json::Value = r.json().await.unwrap();
            (status, retry_after, body, t.elapsed())
        }));
    }
    let mut ok = 0;
    let mut rejected = 0;
    for task in tasks {
        let (status, retry_after, body, elapsed) = task.await.unwrap();
        match status {
            200 => ok += 1,
            429 => {
                rejected += 1;
                assert!(retry_after);
                assert_eq!(body["error_type"], "queue_full");
                assert!(elapsed < Duration::from_secs(5), "a refusal is fast");
            }
            other => panic!("unexpected status {other}: {body}"),
        }
    }
    assert!(ok >= 1 && rejected >= 1, "ok {ok}, rejected {rejected} in {:?}", started.elapsed());
    server.stop().await;
}
