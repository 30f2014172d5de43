//! `cmr-agent synth bench`: where a frame's time goes (camera render with its effects, LiDAR
//! sweep, PNG encode), measured on one sequence of the chosen world and rig without writing
//! anything. Prints figures; asserts nothing.

use std::time::Instant;

use anyhow::Result;

use super::args::WorldArgs;
use super::camera_fx::FrameFx;
use super::generate::{encode_png, SequencePlan};
use super::lidar::scan;
use super::noise::hash;
use super::render::{render, render_with_effects, CameraView};

#[derive(Debug, clap::Args)]
pub struct BenchArgs {
    /// Frames to time (after one warm-up frame).
    #[arg(long, default_value_t = 10)]
    pub frames: usize,
    #[command(flatten)]
    pub world: WorldArgs,
}

pub fn run(args: &BenchArgs) -> Result<()> {
    let config = args.world.config(1, 0, args.frames + 1);
    config.validate()?;
    let started = Instant::now();
    let plan = SequencePlan::new(&config, 0)?;
    let plan_ms = started.elapsed().as_secs_f64() * 1e3;
    let camera_from_lidar = plan.calib.color_camera_from_lidar()?;
    let (w, h) = (plan.rig.width, plan.rig.height);
    let (mut render_ms, mut lidar_ms, mut png_ms, mut rays, mut points_total) = (0.0, 0.0, 0.0, 0usize, 0usize);
    let mut cpu_start = None;
    for i in 0..=args.frames {
        if i == 1 {
            cpu_start = process_cpu_seconds();
        }
        let world_from_lidar = plan.trajectory.world_from_lidar(i);
        let view = CameraView {
            intrinsics: plan.calib.color_intrinsics()?,
            width: w,
            height: h,
            world_from_camera: world_from_lidar.compose(&camera_from_lidar.inverse()),
        };
        let t = Instant::now();
        let rendered = if plan.look.is_some() {
            render_with_effects(&plan.scene, &plan.lighting, &view, hash(&[i as u64]), &FrameFx::draw(hash(&[i as u64, 2]), w as f32 / 1241.0))?
        } else {
            render(&plan.scene, &plan.lighting, &view, hash(&[i as u64]))
        };
        let r = t.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        let points = scan(&plan.scene, &plan.rig.lidar, &world_from_lidar, hash(&[i as u64, 1]));
        let l = t.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        let png = encode_png(&rendered.image)?;
        let p = t.elapsed().as_secs_f64() * 1e3;
        if i > 0 {
            (render_ms, lidar_ms, png_ms) = (render_ms + r, lidar_ms + l, png_ms + p);
            rays += (w * h) as usize + (plan.rig.lidar.beams * plan.rig.lidar.columns) as usize;
            points_total += points.len();
            let _ = png.len();
        }
    }
    let cpu = cpu_start.zip(process_cpu_seconds()).map(|(a, b)| b - a);
    let n = args.frames as f64;
    let total = (render_ms + lidar_ms + png_ms) / n;
    println!("world {}, rig {}: {} shapes, built in {plan_ms:.1} ms", plan.world.name(), plan.rig.name, plan.scene.len());
    println!(
        "per frame ({w}x{h} image, {}x{} LiDAR, {:.0} points, {} threads):",
        plan.rig.lidar.beams,
        plan.rig.lidar.columns,
        points_total as f64 / n,
        rayon::current_num_threads()
    );
    println!("  camera render  {:8.1} ms", render_ms / n);
    println!("  LiDAR sweep    {:8.1} ms", lidar_ms / n);
    println!("  PNG encode     {:8.1} ms", png_ms / n);
    println!("  total          {total:8.1} ms  = {:.2} frames/s ({:.2} M primary rays/s)", 1e3 / total, rays as f64 / n / total / 1e3);
    if let Some(cpu) = cpu {
        // Wall time depends on who else uses the cores; CPU time per frame much less so.
        let per_frame = cpu / n;
        let threads = rayon::current_num_threads() as f64;
        println!("  CPU time       {:8.1} ms per frame  → {:.2} frames/s if {threads} cores were free", per_frame * 1e3, threads / per_frame);
    }
    Ok(())
}

/// User + system CPU seconds of this process so far (Linux `/proc/self/stat`), if readable.
fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name (which is in parentheses and may contain spaces).
    let rest = &stat[stat.rfind(')')? + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    Some((utime + stime) / 100.0)
}
