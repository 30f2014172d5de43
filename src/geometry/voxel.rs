//! Voxel-grid downsampling (as PCL's `VoxelGrid`): the points of each occupied cube of side
//! `voxel_m` are replaced by their centroid (and mean intensity). The grid is aligned with the
//! frame the points are given in: for a stored region, its local frame, whose origin is a
//! multiple of 1 km of the map frame, so cells of a size dividing 1 km line up in both.

/// The smallest and largest voxel side accepted, metres.
pub const MIN_VOXEL_M: f64 = 0.01;
pub const MAX_VOXEL_M: f64 = 100.0;

/// Checks a voxel side (finite, within [`MIN_VOXEL_M`]..=[`MAX_VOXEL_M`]).
pub fn validate_voxel(voxel_m: f64) -> Result<(), String> {
    if !(voxel_m.is_finite() && (MIN_VOXEL_M..=MAX_VOXEL_M).contains(&voxel_m)) {
        return Err(format!("voxel_m must be within {MIN_VOXEL_M}..={MAX_VOXEL_M} m, got {voxel_m}"));
    }
    Ok(())
}

/// One centroid per occupied voxel, ordered by voxel index (x, then y, then z), and the mean
/// intensity when `intensity` is given (one value per point). Points are metres in any frame;
/// non-finite points must have been dropped before. Memory: 16 bytes per input point besides the
/// output. The caller validates `voxel_m` ([`validate_voxel`]).
pub fn voxel_downsample(points: &[[f32; 3]], intensity: Option<&[f32]>, voxel_m: f64) -> (Vec<[f32; 3]>, Option<Vec<f32>>) {
    let inv = 1.0 / voxel_m;
    let cell = |v: f32| ((v as f64) * inv).floor().clamp(i32::MIN as f64, i32::MAX as f64) as i32;
    let mut keyed: Vec<([i32; 3], u32)> = points.iter().enumerate().map(|(i, p)| ([cell(p[0]), cell(p[1]), cell(p[2])], i as u32)).collect();
    keyed.sort_unstable();
    let mut out = Vec::new();
    let mut out_intensity = intensity.map(|_| Vec::new());
    let mut start = 0;
    while start < keyed.len() {
        let key = keyed[start].0;
        let end = start + keyed[start..].iter().take_while(|(k, _)| *k == key).count();
        let mut sum = [0f64; 3];
        let mut isum = 0f64;
        for &(_, i) in &keyed[start..end] {
            let p = points[i as usize];
            for c in 0..3 {
                sum[c] += p[c] as f64;
            }
            if let Some(v) = intensity {
                isum += v[i as usize] as f64;
            }
        }
        let n = (end - start) as f64;
        out.push([(sum[0] / n) as f32, (sum[1] / n) as f32, (sum[2] / n) as f32]);
        if let Some(o) = out_intensity.as_mut() {
            o.push((isum / n) as f32);
        }
        start = end;
    }
    (out, out_intensity)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_centroid_per_occupied_voxel() {
        let points = [[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.5, 0.2, 0.2], [-0.2, 0.0, 0.0], [1.7, 0.4, 0.2]];
        let intensity = [1.0, 3.0, 5.0, 7.0, 9.0];
        let (out, i) = voxel_downsample(&points, Some(&intensity), 1.0);
        assert_eq!(out.len(), 3);
        assert_eq!(out[0], [-0.2, 0.0, 0.0]);
        assert!((out[1][0] - 0.2).abs() < 1e-6 && (out[2][0] - 1.6).abs() < 1e-6);
        assert_eq!(i.unwrap(), vec![7.0, 2.0, 7.0]);
        assert_eq!(voxel_downsample(&points, None, 0.01).0.len(), 5);
        assert!(validate_voxel(0.0).is_err() && validate_voxel(f64::NAN).is_err() && validate_voxel(0.1).is_ok());
    }
}
