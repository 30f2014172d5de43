//! The rig catalogue: named rigs modelled on common vehicle set-ups, and `random`, which draws
//! continuous parameters spanning them. Values are plausible for each sensor family, not copied
//! from any vehicle's calibration.

use rand::Rng;
use serde::{Deserialize, Serialize};

use super::lidar::LidarConfig;
use super::rig::{Rig, KITTI_HEIGHT, KITTI_WIDTH};

/// Every name `--rig` accepts, in `--list-rigs` order (`random` last).
pub const RIG_NAMES: [&str; 5] = ["kitti", "nuscenes", "wide", "vlp16", "os128"];

/// What `--rig` asked for: one named rig for every sequence, or a fresh draw per sequence.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RigChoice {
    Named(Rig),
    Random,
}

impl Default for RigChoice {
    fn default() -> Self {
        RigChoice::Named(named("kitti").expect("kitti rig"))
    }
}

/// Parses a `--rig` value; the error lists the valid names.
pub fn parse_rig(text: &str) -> Result<RigChoice, String> {
    if text == "random" {
        return Ok(RigChoice::Random);
    }
    named(text).map(RigChoice::Named).ok_or_else(|| format!("unknown rig `{text}`; valid rigs: {}, random", RIG_NAMES.join(", ")))
}

fn even(top: f32, bottom: f32, beams: u32) -> LidarConfig {
    LidarConfig { beams, elevation_top_deg: top, elevation_bottom_deg: bottom, ..LidarConfig::default() }
}

/// A 64-beam table, dense around the horizon (where cars and kerbs are) and sparse above and
/// below it: 6 beams from +15° to +5°, 40 from +3° to −5.5°, 18 from −6.5° to −25°.
fn dense_horizon_64() -> Vec<f32> {
    let mut table: Vec<f32> = (0..6).map(|i| 15.0 - 2.0 * i as f32).collect();
    table.extend((0..40).map(|i| 3.0 - 8.5 * i as f32 / 39.0));
    table.extend((0..18).map(|i| -6.5 - 18.5 * i as f32 / 17.0));
    table
}

/// A named rig, or `None`.
pub fn named(name: &str) -> Option<Rig> {
    let rig = match name {
        // KITTI's car: image_2 of sequence 00, an HDL-64E at 10 Hz, level camera.
        "kitti" => Rig {
            name: "kitti".into(),
            width: KITTI_WIDTH,
            height: KITTI_HEIGHT,
            fx: 718.856,
            fy: 718.856,
            cx: 607.1928,
            cy: 185.2157,
            camera_in_lidar_m: [0.27, 0.0, -0.08],
            camera_pitch_deg: 0.0,
            camera_roll_deg: 0.0,
            camera_yaw_deg: 0.0,
            // 6 cm to the left and a KITTI-sized small y term; the z term is 0 so that reading P2
            // as a full projection matrix and the project's t2 convention give the same camera.
            color_offset_m: [0.06, -0.00016, 0.0],
            partner_offsets_m: [[-0.537, 0.0, 0.0], [-0.4727, 0.0033, 0.0]],
            lidar_height_m: 1.73,
            lidar: LidarConfig::default(),
        },
        // A 1600x900 front camera and a 32-beam HDL-32E-like LiDAR at 20 Hz on the roof.
        "nuscenes" => Rig {
            name: "nuscenes".into(),
            width: 1600,
            height: 900,
            fx: 1266.4,
            fy: 1266.4,
            cx: 816.3,
            cy: 491.5,
            camera_in_lidar_m: [0.76, 0.0, -0.33],
            camera_pitch_deg: 0.6,
            camera_roll_deg: -0.3,
            camera_yaw_deg: 0.2,
            color_offset_m: [0.0; 3],
            partner_offsets_m: [[0.0; 3]; 2],
            lidar_height_m: 1.84,
            lidar: LidarConfig { columns: 1084, max_range_m: 70.0, dropout: 0.04, ..even(10.67, -30.67, 32) },
        },
        // A 1920x1200 camera with a long lens, tilted a little, and a 64-beam LiDAR whose beams
        // crowd around the horizon.
        "wide" => Rig {
            name: "wide".into(),
            width: 1920,
            height: 1200,
            fx: 2150.0,
            fy: 2153.0,
            cx: 965.0,
            cy: 603.0,
            camera_in_lidar_m: [0.10, 0.03, -0.40],
            camera_pitch_deg: 1.7,
            camera_roll_deg: 0.4,
            camera_yaw_deg: -1.0,
            color_offset_m: [0.0; 3],
            partner_offsets_m: [[0.0; 3]; 2],
            lidar_height_m: 2.0,
            lidar: LidarConfig {
                columns: 1800,
                max_range_m: 100.0,
                dropout: 0.03,
                elevations_deg: Some(dense_horizon_64()),
                ..even(15.0, -25.0, 64)
            },
        },
        // A 16-beam puck (±15°, 2° apart) above a 1280x720 camera pitched down 3°.
        "vlp16" => Rig {
            name: "vlp16".into(),
            width: 1280,
            height: 720,
            fx: 920.0,
            fy: 920.0,
            cx: 639.5,
            cy: 359.5,
            camera_in_lidar_m: [0.15, 0.0, -0.25],
            camera_pitch_deg: 3.0,
            camera_roll_deg: -0.5,
            camera_yaw_deg: 0.0,
            color_offset_m: [0.0; 3],
            partner_offsets_m: [[0.0; 3]; 2],
            lidar_height_m: 1.8,
            lidar: LidarConfig { columns: 1800, max_range_m: 100.0, range_noise_m: 0.03, ..even(15.0, -15.0, 16) },
        },
        // A 128-beam, ±22.5° LiDAR with 2048 columns above a wide-angle 1920x1080 camera.
        "os128" => Rig {
            name: "os128".into(),
            width: 1920,
            height: 1080,
            fx: 1050.0,
            fy: 1050.0,
            cx: 958.0,
            cy: 545.0,
            camera_in_lidar_m: [0.20, -0.02, -0.30],
            camera_pitch_deg: 2.0,
            camera_roll_deg: 0.8,
            camera_yaw_deg: 0.5,
            color_offset_m: [0.0; 3],
            partner_offsets_m: [[0.0; 3]; 2],
            lidar_height_m: 1.95,
            lidar: LidarConfig { columns: 2048, max_range_m: 120.0, range_noise_m: 0.03, dropout: 0.03, ..even(22.5, -22.5, 128) },
        },
        _ => return None,
    };
    Some(rig)
}

/// A rig with continuous parameters drawn between the named ones: image 960–1920 px wide,
/// horizontal field of view 40°–90°, camera up to 0.8 m ahead of and 0.05–0.45 m below the
/// LiDAR, tilted by up to a few degrees, LiDAR 1.6–2.1 m high with 16–128 beams whose spacing
/// may crowd towards the horizon.
pub fn random_rig(rng: &mut impl Rng) -> Rig {
    let width: u32 = rng.random_range(960..=1920);
    let height = ((width as f64 * rng.random_range(0.3..0.75)).round() as u32).max(240);
    let hfov: f64 = rng.random_range(40f64..90.0).to_radians();
    let fx = width as f64 * 0.5 / (hfov * 0.5).tan();
    let beams: u32 = rng.random_range(16..=128);
    let top: f32 = rng.random_range(2.0..22.0);
    let bottom: f32 = rng.random_range(-31.0..-15.0);
    // Spacing warp: 1 = even; larger crowds beams towards the horizon (0°), blended with even
    // spacing so no two beams come closer than 40 % of the even spacing.
    let gamma: f32 = if rng.random_bool(0.5) { 1.0 } else { rng.random_range(1.2..2.2) };
    let blend: f32 = rng.random_range(0.3..0.6);
    let pivot = top / (top - bottom);
    let elevations: Vec<f32> = (0..beams)
        .map(|b| {
            let k = b as f32 / (beams - 1) as f32;
            let d = k - pivot;
            let span = if d < 0.0 { pivot } else { 1.0 - pivot };
            let x = d.abs() / span;
            let warped = pivot + d.signum() * span * ((1.0 - blend) * x + blend * x.powf(gamma));
            top + (bottom - top) * warped
        })
        .collect();
    let strictly = elevations.windows(2).all(|w| w[0] > w[1]);
    Rig {
        name: "random".into(),
        width,
        height,
        fx,
        fy: fx * rng.random_range(0.997..1.003),
        cx: (width as f64 - 1.0) * 0.5 + rng.random_range(-0.02..0.02) * width as f64,
        cy: (height as f64 - 1.0) * 0.5 + rng.random_range(-0.03..0.03) * height as f64,
        camera_in_lidar_m: [rng.random_range(0.0..0.8), rng.random_range(-0.1..0.1), -rng.random_range(0.05..0.45)],
        camera_pitch_deg: rng.random_range(-1.0..4.0),
        camera_roll_deg: rng.random_range(-1.0..1.0),
        camera_yaw_deg: rng.random_range(-1.5..1.5),
        color_offset_m: [0.0; 3],
        partner_offsets_m: [[0.0; 3]; 2],
        lidar_height_m: rng.random_range(1.6..2.1),
        lidar: LidarConfig {
            beams,
            columns: rng.random_range(1024..=2083),
            elevation_top_deg: top,
            elevation_bottom_deg: bottom,
            max_range_m: rng.random_range(70.0..120.0),
            min_range_m: rng.random_range(1.0..2.5),
            range_noise_m: rng.random_range(0.01..0.04),
            dropout: rng.random_range(0.01..0.06),
            elevations_deg: (gamma != 1.0 && strictly).then_some(elevations),
        },
    }
}

/// `--list-rigs`: every named rig with its parameters, then what `random` spans.
pub fn list() -> String {
    let mut text = String::new();
    for name in RIG_NAMES {
        text.push_str(&named(name).expect("catalogue").describe());
        text.push('\n');
    }
    text.push_str(
        "random    drawn per sequence: image 960–1920 px wide (aspect 0.3–0.75), hfov 40°–90°, camera 0–0.8 m ahead of and \
         0.05–0.45 m below the LiDAR,\n          pitch −1°..+4°, roll ±1°, yaw ±1.5°; LiDAR 1.6–2.1 m high, 16–128 beams from +2..+22° to \
         −15..−31° (even or crowded at the horizon),\n          1024–2083 columns, range noise σ 1–4 cm, dropout 1–6 %\n",
    );
    text
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn every_rig_is_valid_and_random_ones_are_too() {
        for name in RIG_NAMES {
            named(name).unwrap().validate().unwrap();
        }
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for _ in 0..200 {
            random_rig(&mut rng).validate().unwrap();
        }
        assert_eq!(named("wide").unwrap().lidar.elevations().len(), 64);
        let err = parse_rig("hdl64").unwrap_err();
        assert!(err.contains("kitti, nuscenes, wide, vlp16, os128, random"), "{err}");
    }
}
