//! The KITTI-odometry layout: the one module that reads and writes it.
//!
//! A sequence directory holds `velodyne/NNNNNN.bin` (float32 x, y, z, intensity in the velodyne
//! frame), `image_2/NNNNNN.png`, `calib.txt` (`P0`..`P3`, `Tr`) and optionally `poses.txt`
//! (world_from_cam0 per frame). Real KITTI keeps poses in `<root>/poses/NN.txt`; both are found.
//! The synthetic generator writes this layout and the server, evaluator, training and tests read
//! it back through here, so real KITTI and synthetic data take the same code path.

pub mod calib;
pub mod poses;
pub mod sequence;
pub mod velodyne;

pub use calib::Calib;
pub use poses::{read_poses, write_poses};
pub use sequence::{discover_sequences, Frame, Sequence};
pub use velodyne::{read_velodyne, velodyne_to_bytes, write_velodyne, LidarPoint};

/// Formats a number the way KITTI's text files do: `7.215377000000e+02`.
pub fn format_kitti_number(value: f64) -> String {
    // No "-0.000000000000e+00": negative zero prints as zero.
    let value = if value == 0.0 { 0.0 } else { value };
    let formatted = format!("{value:.12e}");
    match formatted.split_once('e') {
        Some((mantissa, exponent)) => {
            let exp: i32 = exponent.parse().unwrap_or(0);
            let sign = if exp < 0 { '-' } else { '+' };
            format!("{mantissa}e{sign}{:02}", exp.abs())
        }
        None => formatted,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_are_written_like_kitti() {
        assert_eq!(format_kitti_number(721.5377), "7.215377000000e+02");
        assert_eq!(format_kitti_number(-0.0027), "-2.700000000000e-03");
        assert_eq!(format_kitti_number(0.0), "0.000000000000e+00");
        assert_eq!(format_kitti_number(-0.0), "0.000000000000e+00");
        assert_eq!("7.215377000000e+02".parse::<f64>().unwrap(), 721.5377);
    }
}
