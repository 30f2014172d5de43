//! The synchronous library API (`agent::prepare_map` / `prepare_image` / `localize`) on real
//! ONNX graphs: the committed tiny contract-following fixture model.

use std::path::PathBuf;

use std::sync::Arc;

use cmr_agent::agent::{self, AxisStarts, SearchConfig};
use cmr_agent::maps::{PreparedMap, prepare_map};
use cmr_agent::geometry::actions::{apply_action, apply_motion};
use cmr_agent::geometry::{ActionFrame, Intrinsics, Pose};
use cmr_agent::model::{Backend, BackendOptions, ModelSet, Points};
use nalgebra::{Matrix3, Vector3};

fn models() -> ModelSet {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model");
    ModelSet::load(&dir, BackendOptions::default()).expect("tiny model loads")
}

/// A street-like cloud in a z-up map frame: ground plane plus two walls.
fn cloud() -> Vec<[f32; 3]> {
    let mut pts = Vec::new();
    for i in 0..120 {
        for j in 0..60 {
            let x = i as f32 * 0.5 - 10.0;
            let y = j as f32 * 0.3 - 9.0;
            pts.push([x, y, -1.7]);
        }
        for h in 0..15 {
            pts.push([i as f32 * 0.5 - 10.0, 6.0, -1.7 + h as f32 * 0.3]);
            pts.push([i as f32 * 0.5 - 10.0, -8.0, -1.7 + h as f32 * 0.3]);
        }
    }
    pts
}

fn rig() -> Pose {
    let r = Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0);
    Pose::from_rt(r, Vector3::new(0.0, -0.08, -0.27))
}

#[test]
fn localize_follows_the_disentangled_update_and_is_deterministic() {
    let set = models();
    let mut backend = set.backend().unwrap();
    let map: Arc<PreparedMap> = Arc::new(prepare_map(&mut backend, Points::xyz(&cloud())).unwrap());
    assert_eq!(map.points.len(), 40960);
    assert_eq!(map.features.len(), 40960 * 64);
    let norms_ok = map.features.chunks(64).all(|f| (f.iter().map(|v| v * v).sum::<f32>() - 1.0).abs() < 1e-3);
    assert!(norms_ok, "point features are L2-normalised");

    let image = image::RgbImage::from_fn(1241, 376, |x, y| image::Rgb([(x % 251) as u8, (y % 253) as u8, ((x + y) % 7) as u8]));
    let k = Intrinsics { fx: 718.856, fy: 718.856, cx: 607.1928, cy: 185.2157 };
    let (tensor, crop_k) = agent::prepare_image(&image, &k, &set.manifest).unwrap();
    assert_eq!(tensor.len(), 3 * 160 * 512);
    assert!((crop_k.fx - 718.856 * 621.0 / 1241.0).abs() < 1e-9);

    let prior = rig().compose(&Pose::ground_motion(0.4, 2.0, -1.0));
    let single = SearchConfig::single(6);
    let a = agent::localize(&mut backend, &map, &tensor, crop_k, prior, single).unwrap();
    let b = agent::localize(&mut backend, &map, &tensor, crop_k, prior, single).unwrap();
    assert_eq!(a.camera_from_map(), b.camera_from_map());
    assert_eq!((a.hypotheses.len(), a.chosen), (1, 0));
    let best = a.best();
    assert!(best.steps.len() >= 1 && best.steps.len() <= 6);
    assert_eq!(best.converged, best.steps.last().unwrap().action.is_zero());
    let mut pose = prior;
    for step in &best.steps {
        pose = apply_action(ActionFrame::CameraY, &pose, &map.pivot, &step.action);
        assert_eq!(pose, step.camera_from_map);
        assert!((-1.0..=1.0).contains(&step.alignment), "every step is scored: {}", step.alignment);
        for row in &step.probabilities {
            assert!((row.iter().sum::<f32>() - 1.0).abs() < 1e-4);
        }
    }
    assert_eq!(pose, a.camera_from_map());
    assert!((0.0..=1.0).contains(&a.confidence.score));
    assert_eq!(a.confidence.alignment, best.alignment());

    // Four starts: the first is the single trajectory above (same rows, batched with three more),
    // the others start from the prior turned about the pivot, and the answer is the best score.
    let four = SearchConfig { hypotheses: 4, max_iterations: 6, narrow_after: None, merge_duplicates: false, keep_prior: false, prior_bound: None, refine: false, polish: false, prior_margin: 0.0, axis: AxisStarts::NONE, judge_zoom: 0.0, judge_gate: 1.0 };
    let multi = agent::localize(&mut backend, &map, &tensor, crop_k, prior, four).unwrap();
    assert_eq!(multi.hypotheses.len(), 4);
    let first = &multi.hypotheses[0];
    assert_eq!(first.steps.len(), best.steps.len());
    assert!((first.camera_from_map().matrix() - best.camera_from_map().matrix()).abs().max() < 1e-9);
    for (h, offset) in multi.hypotheses.iter().zip([0.0, 90.0, 180.0, -90.0]) {
        assert_eq!(h.start_yaw_offset_deg, offset);
        let turned = apply_motion(ActionFrame::CameraY, &prior, &map.pivot, offset, 0.0, 0.0);
        assert!((h.start.matrix() - turned.matrix()).abs().max() < 1e-12, "start {offset}");
        assert!(multi.best().alignment() >= h.alignment());
    }
    let finals: Vec<f32> = multi.hypotheses.iter().map(|h| h.alignment()).collect();
    assert_eq!(multi.chosen, agent::best_of(finals));
    assert_eq!(multi.pose_after(multi.iterations()), multi.camera_from_map());
    assert!(multi.hypotheses.iter().all(|h| !h.dropped));

    // Narrowed after 2 steps: the same first two steps, then only the leader at that point goes
    // on; the dropped ones keep their 2-step pose and still compete at the end.
    let narrowed = agent::localize(&mut backend, &map, &tensor, crop_k, prior, SearchConfig { narrow_after: Some(2), ..four }).unwrap();
    let went_on: Vec<usize> = (0..4).filter(|&h| !narrowed.hypotheses[h].dropped).collect();
    let scores_at_2: Vec<f32> = multi.hypotheses.iter().map(|h| h.pose_after(2).1).collect();
    let leader = agent::best_of(scores_at_2);
    for (h, (n, m)) in narrowed.hypotheses.iter().zip(&multi.hypotheses).enumerate() {
        let shared = n.steps.len().min(2);
        assert!((n.pose_after(shared).0.matrix() - m.pose_after(shared).0.matrix()).abs().max() < 1e-9, "hypothesis {h}");
        if n.dropped {
            assert_eq!(n.steps.len(), 2);
            assert_ne!(h, leader);
        } else if h != leader {
            assert!(m.steps.len() <= 2, "only the leader and those already done are not dropped");
        }
    }
    assert!(went_on.contains(&leader));
    let finals: Vec<f32> = narrowed.hypotheses.iter().map(|h| h.alignment()).collect();
    assert_eq!(narrowed.chosen, agent::best_of(finals));

    // A bounded prior: the starts turn about the prior's camera centre within the bound, and
    // the answer is the best-scoring pose visited inside the bound, with its steps up to there.
    let bound = agent::PriorBound { rotation_deg: 30.0, translation_m: 5.0 };
    let bounded = agent::localize(&mut backend, &map, &tensor, crop_k, prior, SearchConfig { prior_bound: Some(bound), ..four }).unwrap();
    let centre = nalgebra::Point3::from(prior.camera_position_in_map());
    for (h, offset) in bounded.hypotheses.iter().zip([0.0, 30.0, -30.0, 15.0]) {
        assert_eq!(h.start_yaw_offset_deg, offset);
        let turned = apply_motion(ActionFrame::CameraY, &prior, &centre, offset, 0.0, 0.0);
        assert!((h.start.matrix() - turned.matrix()).abs().max() < 1e-12, "start {offset}");
        assert!(bound.contains(&prior, &h.start), "start {offset} inside the bound");
    }
    let answer = bounded.camera_from_map();
    assert!(bound.contains(&prior, &answer));
    let score = bounded.confidence.alignment;
    let mut inside = 0;
    for h in &bounded.hypotheses {
        for k in 0..=h.steps.len() {
            let (pose, s) = h.pose_after(k);
            if bound.contains(&prior, &pose) {
                inside += 1;
                assert!(s <= score, "a visited pose inside the bound scores {s} > the answer's {score}");
            }
        }
    }
    assert!(inside >= 4, "every start is inside");
    if bounded.kept_prior {
        assert_eq!((answer, bounded.answer_steps().len()), (prior, 0));
    } else {
        assert_eq!(bounded.answer_steps().last().map_or(bounded.best().start, |s| s.camera_from_map), answer);
    }
    assert_eq!(bounded.pose_after(bounded.iterations()), answer);
    assert!(bounded.polish.is_none());

    // The same search polished: the search's answer is the same, the polish moves it only to
    // poses that score higher, within its reach and the bound.
    let polished = agent::localize(&mut backend, &map, &tensor, crop_k, prior, SearchConfig { prior_bound: Some(bound), polish: true, ..four }).unwrap();
    let p = polished.polish.expect("a bounded search polishes");
    assert_eq!((polished.search_answer(), p.from, p.from_alignment), (answer, answer, score));
    assert_eq!(polished.camera_from_map(), p.camera_from_map);
    assert_eq!(polished.pose_after(polished.iterations()), p.camera_from_map);
    assert!(p.alignment >= p.from_alignment && p.scores > 0);
    assert!(p.scores <= p.candidates * agent::polish::MAX_SCORES);
    assert!(bound.contains(&prior, &p.camera_from_map) && agent::polish::REACH.contains(&answer, &p.camera_from_map));
    assert_eq!(polished.signals(), bounded.signals(), "the verdict reads the search's answer");
    // A single start without a bound never polishes (track's small searches).
    let single = agent::localize(&mut backend, &map, &tensor, crop_k, prior, SearchConfig { polish: true, ..SearchConfig::single(3) }).unwrap();
    assert!(single.polish.is_none());
}

#[test]
fn bad_inputs_are_refused() {
    let set = models();
    let mut backend = set.backend().unwrap();
    assert!(prepare_map(&mut backend, Points::xyz(&[])).is_err());
    let image = image::RgbImage::new(64, 32);
    let bad = Intrinsics { fx: -1.0, fy: 1.0, cx: 0.0, cy: 0.0 };
    assert!(agent::prepare_image(&image, &bad, &set.manifest).is_err());
    let nan = Intrinsics { fx: f64::NAN, fy: 1.0, cx: 0.0, cy: 0.0 };
    assert!(agent::prepare_image(&image, &nan, &set.manifest).is_err());
}

/// Starts along the optical axis in one search answer as the best of separate searches from
/// each shifted prior would (the tracker's loop before 2026-12-06): the same trajectories, the
/// same answer and, read from its own group, the same calibrator signals.
#[test]
fn axis_starts_answer_as_the_best_of_separate_searches() {
    let set = models();
    let mut backend = set.backend().unwrap();
    let map = Arc::new(prepare_map(&mut backend, Points::xyz(&cloud())).unwrap());
    let image = image::RgbImage::from_fn(640, 200, |x, y| image::Rgb([(x * 3) as u8, (y * 5) as u8, ((x + y) % 11 * 20) as u8]));
    let (tensor, crop_k) = agent::prepare_image(&image, &Intrinsics { fx: 500.0, fy: 500.0, cx: 319.5, cy: 99.5 }, &set.manifest).unwrap();
    let prior = rig().compose(&Pose::ground_motion(0.2, 1.0, -0.5));
    let base = SearchConfig { hypotheses: 2, keep_prior: true, merge_duplicates: true, ..SearchConfig::single(3) };
    for margin in [0.0, 0.005, 1.0] {
        let axis = AxisStarts { each_way: 2, step_m: 1.25, margin };
        let one = agent::localize(&mut backend, &map, &tensor, crop_k, prior, SearchConfig { axis, ..base }).unwrap();
        assert_eq!(one.hypotheses.len(), 2 * 5);
        let mut best: Option<(agent::Localization, f64, f32)> = None;
        for (g, (d, start)) in axis.priors(&prior).into_iter().enumerate() {
            let alone = agent::localize(&mut backend, &map, &tensor, crop_k, start, base).unwrap();
            for (h, (a, b)) in one.hypotheses[2 * g..2 * g + 2].iter().zip(&alone.hypotheses).enumerate() {
                assert_eq!((a.start_axis_shift_m, a.steps.len(), a.dropped), (d, b.steps.len(), b.dropped), "group {g}, start {h}");
                assert!((a.camera_from_map().matrix() - b.camera_from_map().matrix()).abs().max() < 1e-9, "group {g}, start {h}");
            }
            let judged = alone.confidence.alignment + if d == 0.0 { margin } else { 0.0 };
            if best.as_ref().is_none_or(|(_, _, b)| judged > *b) {
                best = Some((alone, d, judged));
            }
        }
        let (alone, d, _) = best.unwrap();
        assert_eq!((one.best().start_axis_shift_m, one.kept_prior, one.answer_steps), (d, alone.kept_prior, alone.answer_steps), "margin {margin}");
        assert!((one.camera_from_map().matrix() - alone.camera_from_map().matrix()).abs().max() < 1e-9, "margin {margin}");
        let (a, b) = (one.signals(), alone.signals());
        assert!((a.alignment - b.alignment).abs() < 1e-6 && a.log2_starts == b.log2_starts && a.agreement == b.agreement && (a.visit_share - b.visit_share).abs() < 1e-12, "{a:?} against {b:?}");
        match margin {
            0.0 => assert_ne!(d, 0.0, "without a margin this image is best explained from a shifted prior"),
            _ => assert_eq!(d, 0.0, "a margin of 0.005 or more keeps the prior's own answer here"),
        }
    }
}

/// Requests stepped together in one batched policy call get exactly the answers they get alone.
#[test]
fn batched_workers_match_the_synchronous_loop() {
    use cmr_agent::serving::scheduler::{Job, Scheduler, SchedulerConfig};
    use std::time::{Duration, Instant};

    let set = models();
    let mut backend = set.backend().unwrap();
    let map = Arc::new(prepare_map(&mut backend, Points::xyz(&cloud())).unwrap());
    let k = Intrinsics { fx: 500.0, fy: 500.0, cx: 319.5, cy: 99.5 };
    let cases: Vec<(Vec<f32>, Intrinsics, Pose, SearchConfig)> = (0..6)
        .map(|i| {
            let image = image::RgbImage::from_fn(640, 200, |x, y| image::Rgb([(x * (i + 1)) as u8, (y * 3) as u8, (i * 40) as u8]));
            let (tensor, crop_k) = agent::prepare_image(&image, &k, &set.manifest).unwrap();
            let prior = rig().compose(&Pose::ground_motion(0.3 * i as f64, i as f64, -1.0));
            // Searches of 1 to 3 starts (one narrowed): the 8-row batch holds some, the rest wait.
            let narrow_after = (i == 4).then_some(1);
            let merge_duplicates = i == 5;
            (tensor, crop_k, prior, SearchConfig { hypotheses: 1 + i as usize % 3, max_iterations: 3 + i as usize, narrow_after, merge_duplicates, keep_prior: i % 2 == 0, prior_bound: None, refine: i % 3 == 1, polish: i % 2 == 1, prior_margin: if i % 4 == 0 { 0.03 } else { 0.0 }, axis: if i == 3 { AxisStarts { each_way: 1, step_m: 1.25, margin: 0.005 } } else { AxisStarts::NONE }, judge_zoom: 0.0, judge_gate: 1.0 })
        })
        .collect();
    let expected: Vec<_> = cases
        .iter()
        .map(|(t, ck, prior, n)| agent::localize(&mut backend, &map, t, *ck, *prior, *n).unwrap())
        .collect();

    let scheduler = Scheduler::start(&set.factory(), SchedulerConfig { workers: 1, max_batch: 8, queue_capacity: 16 }).unwrap();
    let mut answers = Vec::new();
    for (tensor, crop_k, prior, search) in cases {
        let (reply, answer) = tokio::sync::oneshot::channel();
        let start = agent::Start { maps: vec![map.clone()], image_tensor: tensor, intrinsics: crop_k, prior, search, views: Vec::new() };
        let job = Job { start, deadline: Instant::now() + Duration::from_secs(30), span: tracing::Span::none(), reply };
        let slot = scheduler.reserve().ok().expect("room");
        scheduler.submit(job, slot).ok().expect("queued");
        answers.push(answer);
    }
    for (answer, want) in answers.into_iter().zip(&expected) {
        let got = answer.blocking_recv().unwrap().ok().expect("localized").localization;
        assert_eq!((got.hypotheses.len(), got.chosen), (want.hypotheses.len(), want.chosen));
        for (g, w) in got.hypotheses.iter().zip(&want.hypotheses) {
            assert_eq!(g.steps.len(), w.steps.len());
            let diff = (g.camera_from_map().matrix() - w.camera_from_map().matrix()).abs().max();
            assert!(diff < 1e-9, "batched result differs by {diff}");
        }
        // The polished answer too (cases 1 and 5 polish; case 3 is a single start from each of three
        // priors along the axis, which does not).
        assert_eq!(got.polish.is_some(), want.polish.is_some());
        let diff = (got.camera_from_map().matrix() - want.camera_from_map().matrix()).abs().max();
        assert!(diff < 1e-9, "batched answer differs by {diff}");
    }
    let stats = scheduler.batch_stats();
    assert!(stats.largest_batch > 3, "requests were stepped together: {stats:?}");
    assert!(stats.largest_batch <= 8, "the batch holds at most max_batch rows: {stats:?}");
    assert!(scheduler.shutdown(Duration::from_secs(5)));
}

/// `cmr-agent localize` answers with the same JSON shape as the HTTP API.
#[test]
fn localize_subcommand_prints_a_response() {
    let dir = tempfile::tempdir().unwrap();
    let cloud = cmr_agent::maps::formats::PointCloud { xyz: cloud(), intensity: None };
    std::fs::write(dir.path().join("street.bin"), cmr_agent::maps::formats::write_kitti_bin(&cloud)).unwrap();
    let image = image::RgbImage::from_fn(640, 200, |x, y| image::Rgb([(x % 200) as u8, (y % 100) as u8, 90]));
    let mut png = std::io::Cursor::new(Vec::new());
    image.write_to(&mut png, image::ImageFormat::Png).unwrap();
    use base64::Engine;
    let request = serde_json::json!({
        "image": base64::engine::general_purpose::STANDARD.encode(png.into_inner()),
        "intrinsics": {"fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 99.5},
        "max_iterations": 3,
    });
    std::fs::write(dir.path().join("request.json"), request.to_string()).unwrap();
    let models = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model");
    let localize = |map: &str| {
        std::process::Command::new(env!("CARGO_BIN_EXE_cmr-agent"))
            .args(["localize", "--models", models.to_str().unwrap(), "--map"])
            .arg(dir.path().join(map))
            .arg("--request")
            .arg(dir.path().join("request.json"))
            .output()
            .unwrap()
    };
    let out = localize("street.bin");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let response: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(response["map_id"], "street");
    let iterations = response["iterations"].as_u64().unwrap();
    assert!(iterations <= 3, "a first-round answer takes 1-3 steps, a refinement start's up to 3");
    assert_eq!(response["trajectory"].as_array().unwrap().len() as u64, iterations);

    let bad = localize("missing.bin");
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("missing.bin"));
}

/// Start-up problems stop `serve` at once with one message naming the cause.
#[test]
fn serve_refuses_a_missing_runtime_or_an_unknown_manifest() {
    let models = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model");
    let maps = tempfile::tempdir().unwrap();
    let run = |models: &std::path::Path, extra: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_cmr-agent"))
            .args(["serve", "--host", "127.0.0.1", "--port", "0", "--models", models.to_str().unwrap(), "--maps", maps.path().to_str().unwrap()])
            .args(extra)
            .output()
            .unwrap();
        assert!(!out.status.success());
        String::from_utf8_lossy(&out.stderr).to_string()
    };
    let err = run(&models, &["--ort-lib", "/nonexistent/libonnxruntime.so"]);
    assert!(err.contains("ONNX Runtime") && err.contains("/nonexistent/libonnxruntime.so"), "{err}");

    let dir = tempfile::tempdir().unwrap();
    for entry in std::fs::read_dir(&models).unwrap() {
        let entry = entry.unwrap();
        std::fs::copy(entry.path(), dir.path().join(entry.file_name())).unwrap();
    }
    let manifest = std::fs::read_to_string(dir.path().join("manifest.json")).unwrap().replace("cmr-agent-manifest/1", "cmr-agent-manifest/9");
    std::fs::write(dir.path().join("manifest.json"), manifest).unwrap();
    let err = run(dir.path(), &[]);
    assert!(err.contains("unknown format") && err.contains("cmr-agent-manifest/9"), "{err}");
}

/// The image the judge's tests search with: KITTI-sized, patterned, with KITTI's intrinsics.
fn judged_image() -> (image::RgbImage, Intrinsics) {
    let image = image::RgbImage::from_fn(1241, 376, |x, y| image::Rgb([(x % 251) as u8, (y % 253) as u8, ((x * y) % 13) as u8]));
    (image, Intrinsics { fx: 718.856, fy: 718.856, cx: 607.1928, cy: 185.2157 })
}

/// The judge's views: the visited pose whose alignment score, averaged over the served crop and
/// the three zoomed ones, is highest (recomputed here from the views' own image features) places
/// the answer: the visited pose near it that the served crop scores highest; the polish climbs
/// the served score from there.
#[test]
fn the_judges_views_choose_among_every_visited_pose() {
    let set = models();
    let mut backend = set.backend().unwrap();
    let map: Arc<PreparedMap> = Arc::new(prepare_map(&mut backend, Points::xyz(&cloud())).unwrap());
    let (image, k) = judged_image();
    let (tensor, crop_k) = agent::prepare_image(&image, &k, &set.manifest).unwrap();
    // At zoom 1 the centre view is the served crop; at 0 there are none; below 1 is refused.
    let same = agent::prepare_views(&image, &k, &set.manifest, 1.0).unwrap();
    assert_eq!((same[1].tensor == tensor, same[1].intrinsics), (true, crop_k));
    assert!(agent::prepare_views(&image, &k, &set.manifest, 0.0).unwrap().is_empty());
    assert!(agent::prepare_views(&image, &k, &set.manifest, 0.5).is_err());
    let views = agent::prepare_views(&image, &k, &set.manifest, 1.5).unwrap();
    assert_eq!(views.len(), 3);
    // The left crop sees the principal point further right, the right crop further left.
    assert!((views[1].intrinsics.fx / crop_k.fx - 1.5).abs() < 0.01);
    assert!(views[0].intrinsics.cx > views[1].intrinsics.cx + 100.0 && views[2].intrinsics.cx < views[1].intrinsics.cx - 100.0);

    let prior = rig().compose(&Pose::ground_motion(0.5, 2.0, -1.0));
    let four = SearchConfig { hypotheses: 4, max_iterations: 6, narrow_after: None, merge_duplicates: false, keep_prior: true, prior_bound: None, refine: false, polish: false, prior_margin: 0.0, axis: AxisStarts::NONE, judge_zoom: 1.5, judge_gate: 1.0 };
    let start = |search: SearchConfig, views: Vec<agent::ViewInput>| agent::Start { maps: vec![map.clone()], image_tensor: tensor.clone(), intrinsics: crop_k, prior, search, views };
    let judged = agent::localize_start(&mut backend, start(four, views.clone())).unwrap();
    assert!(judged.timings.judge_ms > 0.0);

    let layout = agent::StateLayout::from_manifest(&set.manifest);
    let grids: Vec<(agent::ImageGrid, Intrinsics)> = views.iter().map(|v| (agent::ImageGrid::new(&layout, backend.encode_image(&v.tensor).unwrap()), v.intrinsics)).collect();
    let mut scratch = agent::ScatterScratch::default();
    let mut average = |pose: &Pose, served: f32| {
        let sum: f64 = grids.iter().map(|(g, vk)| agent::state::alignment(&layout, &map.points, &map.features, g, vk, pose, &mut scratch) as f64).sum();
        ((served as f64 + sum) / 4.0) as f32
    };
    let (answer, served) = judged.best().pose_after(judged.answer_steps);
    assert_eq!(answer, judged.camera_from_map(), "unpolished");
    // The judge's pose: the visited pose with the highest average (the first on a draw); the
    // answer: among the visited poses near it, the one the served view scores highest.
    let visited: Vec<(Pose, f32)> = judged.hypotheses.iter().flat_map(|h| (0..=h.steps.len()).map(move |k| h.pose_after(k))).collect();
    assert!(visited.len() > 4);
    let averages: Vec<f32> = visited.iter().map(|(pose, s)| average(pose, *s)).collect();
    let top = averages.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let judge_pose = visited[averages.iter().position(|a| *a == top).unwrap()].0;
    assert!(agent::search::JUDGE_LOCAL.contains(&judge_pose, &answer));
    for (pose, s) in &visited {
        if agent::search::JUDGE_LOCAL.contains(&judge_pose, pose) {
            assert!(*s <= served, "a visited pose near the judge's scores {s} > the answer's {served} in the served view");
        }
    }
    assert!(average(&answer, served) <= top);

    // Polished: the judge's answer is the first candidate; each climbs on the served score and
    // never descends.
    let polished = agent::localize_start(&mut backend, start(SearchConfig { polish: true, ..four }, views.clone())).unwrap();
    let p = polished.polish.expect("a multi-start search polishes");
    assert!(p.alignment >= p.from_alignment);
    if p.from == answer {
        assert_eq!(p.from_alignment, served);
    }
    // A search that judges needs its views.
    assert!(agent::localize_start(&mut backend, start(four, Vec::new())).is_err());
    // Without a judge zoom the views are not read: the served search's answer.
    let plain = SearchConfig { judge_zoom: 0.0, ..four };
    let a = agent::localize_start(&mut backend, start(plain, views)).unwrap();
    let b = agent::localize(&mut backend, &map, &tensor, crop_k, prior, plain).unwrap();
    assert_eq!((a.camera_from_map(), a.timings.judge_ms), (b.camera_from_map(), 0.0));
}

/// The judge's gate: the views are encoded when the search finishes, and only when at most
/// `judge_gate` of the other starts ended where the served search answers; unread, the served
/// crop's best visited pose answers. Views whose tensors the encoder refuses show which: a search
/// that reads them fails, one that does not answers.
#[test]
fn the_judges_views_are_read_only_when_the_starts_disagree() {
    let set = models();
    let mut backend = set.backend().unwrap();
    let map: Arc<PreparedMap> = Arc::new(prepare_map(&mut backend, Points::xyz(&cloud())).unwrap());
    let (image, k) = judged_image();
    let (tensor, crop_k) = agent::prepare_image(&image, &k, &set.manifest).unwrap();
    let views = agent::prepare_views(&image, &k, &set.manifest, 1.5).unwrap();
    let broken: Vec<agent::ViewInput> = views.iter().map(|v| agent::ViewInput { tensor: vec![0.0; 7], intrinsics: v.intrinsics }).collect();
    // Within a bound of 10° the starts lie within 20° of each other: after two steps some still
    // end together.
    let prior = rig().compose(&Pose::ground_motion(0.0, 0.5, 0.0));
    let bound = agent::PriorBound { rotation_deg: 10.0, translation_m: 5.0 };
    let four = SearchConfig { hypotheses: 4, max_iterations: 2, narrow_after: None, merge_duplicates: true, keep_prior: true, prior_bound: Some(bound), refine: false, polish: false, prior_margin: 0.0, axis: AxisStarts::NONE, judge_zoom: 1.5, judge_gate: 1.0 };
    let start = |search: SearchConfig, views: Vec<agent::ViewInput>| agent::Start { maps: vec![map.clone()], image_tensor: tensor.clone(), intrinsics: crop_k, prior, search, views };

    let always = agent::localize_start(&mut backend, start(four, views.clone())).unwrap();
    let record = always.judge.expect("a judging search records its judge");
    assert!(record.read_views && always.timings.judge_ms > 0.0);
    let served = agent::localize(&mut backend, &map, &tensor, crop_k, prior, SearchConfig { judge_zoom: 0.0, ..four }).unwrap();
    assert!(served.judge.is_none());
    let search_answer = served.search_answer();
    let expected = agent::search::start_agreement(&served.hypotheses, served.chosen, served.kept_prior, &search_answer);
    assert_eq!(record.agreement, expected);
    assert!(record.agreement > 0.0, "this fixture's starts should agree in part ({})", record.agreement);
    // Read (gate 1), broken views fail the request at its end.
    assert!(agent::localize_start(&mut backend, start(four, broken.clone())).is_err());

    // Gate below the agreement: never encoded, so broken views do no harm, and the served
    // crop's best pose visited inside the bound answers.
    let gated = agent::localize_start(&mut backend, start(SearchConfig { judge_gate: record.agreement / 2.0, ..four }, broken)).unwrap();
    assert_eq!(gated.judge.map(|j| (j.agreement, j.read_views)), Some((record.agreement, false)));
    let visited: Vec<(Pose, f32)> = gated.hypotheses.iter().flat_map(|h| (0..=h.steps.len()).map(move |k| h.pose_after(k))).filter(|(pose, _)| bound.contains(&prior, pose)).collect();
    let top = visited.iter().map(|(_, s)| *s).fold(f32::NEG_INFINITY, f32::max);
    assert_eq!(gated.best().pose_after(gated.answer_steps).1, top);
    // At the agreement itself the views are read: the same answer as always.
    let at = agent::localize_start(&mut backend, start(SearchConfig { judge_gate: record.agreement, ..four }, views)).unwrap();
    assert_eq!((at.camera_from_map(), at.judge.map(|j| j.read_views)), (always.camera_from_map(), Some(true)));
}
