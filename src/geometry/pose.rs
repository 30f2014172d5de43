//! Rigid poses (`camera_from_map`) and the conversions the API and file formats need.

use nalgebra::{Isometry3, Matrix3, Matrix4, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// A rigid transform p_out = R p_in + t. Used for `camera_from_map`, KITTI's `Tr` and poses.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose(pub Isometry3<f64>);

impl Pose {
    pub fn identity() -> Self {
        Pose(Isometry3::identity())
    }

    pub fn from_rt(rotation: Matrix3<f64>, translation: Vector3<f64>) -> Self {
        let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&rotation));
        Pose(Isometry3::from_parts(Translation3::from(translation), rotation))
    }

    /// From a row-major 3x4 `[R | t]`, the layout KITTI's calib.txt and poses.txt use.
    /// Errors: R is not a rotation ([`check_rotation`]; the message starts "is not a rotation").
    pub fn from_row_major_3x4(values: &[f64; 12]) -> Result<Self, String> {
        let r = Matrix3::new(
            values[0], values[1], values[2], values[4], values[5], values[6], values[8], values[9],
            values[10],
        );
        check_rotation(&r)?;
        Ok(Self::from_rt(r, Vector3::new(values[3], values[7], values[11])))
    }

    pub fn to_row_major_3x4(&self) -> [f64; 12] {
        let m = self.matrix();
        let mut out = [0.0; 12];
        for row in 0..3 {
            for col in 0..4 {
                out[row * 4 + col] = m[(row, col)];
            }
        }
        out
    }

    /// From a row-major 4x4 matrix (a map-frame camera_from_map). Each entry must lie within its
    /// [`entry_bounds`] (what the API's `Matrix4x4` schema states: rotation entries within
    /// ±[`MAX_ROTATION_ENTRY`], translation within ±[`MAX_TRANSLATION_M`] m, the last row
    /// (0, 0, 0, 1) within [`LAST_ROW_TOLERANCE`]); then R must be a rotation
    /// ([`check_rotation`]), and the camera's position −Rᵀt within
    /// ±[`MAX_COORDINATE_M`] on each axis, the bound of every map-frame coordinate (these two
    /// relate entries to each other, which a JSON Schema cannot state).
    pub fn from_matrix(m: &[[f64; 4]; 4]) -> Result<Self, String> {
        if m.iter().flatten().any(|v| !v.is_finite()) {
            return Err("pose contains a non-finite value".into());
        }
        // Translation first, so a huge translation is named as such; then the last row. The
        // rotation entries' bound (±MAX_ROTATION_ENTRY) needs no pass of its own: an entry beyond
        // it puts a diagonal entry of RᵀR above 1 + ROTATION_TOLERANCE, which `check_rotation`
        // refuses, naming what is wrong the way every other reader of rotations does.
        for (row, col) in (0..3).map(|r| (r, 3)).chain((0..4).map(|c| (3, c))) {
            let (low, high) = entry_bounds(row, col);
            let v = m[row][col];
            if !(low..=high).contains(&v) {
                return Err(match (row, col) {
                    (3, _) => format!("pose's last row must be [0, 0, 0, 1] (each within {LAST_ROW_TOLERANCE:e}), has {v} at column {col}"),
                    _ => format!("pose's translation is beyond ±{MAX_TRANSLATION_M:e} m ({v} in row {row})"),
                });
            }
        }
        let r = Matrix3::new(m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2]);
        check_rotation(&r).map_err(|e| format!("pose's rotation block {e}"))?;
        let pose = Self::from_rt(r, Vector3::new(m[0][3], m[1][3], m[2][3]));
        let c = pose.camera_position_in_map();
        if c.iter().any(|v| v.abs() > MAX_COORDINATE_M) {
            return Err(format!("pose's camera position ({:.1}, {:.1}, {:.1}) m is beyond ±{MAX_COORDINATE_M:e} m", c.x, c.y, c.z));
        }
        Ok(pose)
    }

    /// Finite, with every translation component within ±[`MAX_COORDINATE_M`]: what the agent
    /// can step from (the step loop checks every pose it reaches, in the region's local frame,
    /// where coordinates are small: see `geometry::frame`).
    pub fn is_sane(&self) -> bool {
        let t = self.0.translation.vector;
        let q = self.0.rotation.coords;
        t.iter().all(|v| v.is_finite() && v.abs() <= MAX_COORDINATE_M) && q.iter().all(|v| v.is_finite())
    }

    pub fn matrix(&self) -> Matrix4<f64> {
        self.0.to_homogeneous()
    }

    /// The same pose with its rotation quaternion scaled back to unit length: products of many
    /// poses (a chain of predictions) drift from a rotation by rounding.
    pub fn renormalized(&self) -> Self {
        let q = UnitQuaternion::new_normalize(self.0.rotation.into_inner());
        Pose(Isometry3::from_parts(self.0.translation, q))
    }

    pub fn to_rows(&self) -> [[f64; 4]; 4] {
        let m = self.matrix();
        std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
    }

    pub fn rotation(&self) -> Matrix3<f64> {
        self.0.rotation.to_rotation_matrix().into_inner()
    }

    pub fn translation(&self) -> Vector3<f64> {
        self.0.translation.vector
    }

    pub fn inverse(&self) -> Self {
        Pose(self.0.inverse())
    }

    /// `self ∘ other`: first `other`, then `self`.
    pub fn compose(&self, other: &Pose) -> Self {
        Pose(self.0 * other.0)
    }

    pub fn transform(&self, p: &Point3<f64>) -> Point3<f64> {
        self.0 * p
    }

    /// The camera centre in the map frame when `self` is camera_from_map: -Rᵀ t.
    pub fn camera_position_in_map(&self) -> Vector3<f64> {
        self.0.inverse().translation.vector
    }

    /// The heading of the camera's optical axis in the map's ground plane, in degrees,
    /// counter-clockwise from the map's +x axis (0 = looking along +x, 90 = along +y).
    pub fn camera_heading_in_map_deg(&self) -> f64 {
        let forward_in_map = self.rotation().transpose() * Vector3::z();
        forward_in_map.y.atan2(forward_in_map.x).to_degrees()
    }

    /// camera_from_map of a level camera (camera y = map −z) at `position` (map frame, metres)
    /// whose optical axis points along the map's +x axis: a KITTI-like rig at its LiDAR, the
    /// localize default for a region with no prior (`serving::PriorSource::Default`).
    pub fn level_camera_along_x(position: Vector3<f64>) -> Self {
        let r = Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0);
        Self::from_rt(r, -(r * position))
    }

    /// A rotation by `angle_rad` about the map's z axis followed by a translation: the
    /// ground-plane perturbation of the paper's protocol.
    pub fn ground_motion(yaw_rad: f64, dx: f64, dy: f64) -> Self {
        Pose(Isometry3::from_parts(
            Translation3::new(dx, dy, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw_rad),
        ))
    }
}

/// How far a 3x3 block may be from a rotation and still be read as one: every entry of RᵀR − I
/// within ±this (dimensionless). Text files keep 6 to 13 significant digits (KITTI's poses.txt
/// about 7, so ~1e-6 off), well inside; a scaled (R00 = 2), sheared, zeroed (a lost track) or
/// half-written block is far outside. Python's twin is `geometry.ROTATION_TOLERANCE`; both are
/// pinned by fixtures/conventions.json.
pub const ROTATION_TOLERANCE: f64 = 1e-3;

/// Whether `r` is a rotation: finite, orthonormal (every entry of RᵀR − I within
/// ±[`ROTATION_TOLERANCE`]) and det R = +1. The determinant is checked by its sign: with RᵀR
/// within the tolerance of I, det R is ±1 to within 1.5 × the tolerance, so a negative one is a
/// reflection. This is the one check of every rotation the project reads: the API's priors and
/// regions' `initial_camera_from_map`, KITTI's calib `Tr` / `R0_rect` and poses.txt (map build,
/// track, eval, synth); `geometry.check_rotation` in training/cmr/geometry.py is its twin, with
/// the same messages.
///
/// Errors: a message that starts "is not a rotation: " and says what is wrong (a non-finite
/// entry; every entry 0; the rows' lengths and how far RᵀR is from I; a negative determinant),
/// to be prefixed by the caller with what was read (file and line, or field).
pub fn check_rotation(r: &Matrix3<f64>) -> Result<(), String> {
    if r.iter().any(|v| !v.is_finite()) {
        return Err("is not a rotation: it has a non-finite entry".into());
    }
    if r.iter().all(|&v| v == 0.0) {
        return Err("is not a rotation: every entry is 0 (an unset pose, such as a lost track)".into());
    }
    let deviation = (r.transpose() * r - Matrix3::identity()).abs().max();
    if deviation > ROTATION_TOLERANCE {
        let len = |i: usize| r.row(i).norm();
        return Err(format!(
            "is not a rotation: its rows have lengths {:.4}, {:.4}, {:.4} and RᵀR differs from the identity by up to {deviation:.4} (tolerance {ROTATION_TOLERANCE})",
            len(0),
            len(1),
            len(2)
        ));
    }
    let det = r.determinant();
    if det < 0.0 {
        return Err(format!("is not a rotation: its determinant is {det:.4}, a reflection (a rotation's is +1)"));
    }
    Ok(())
}

/// The largest map-frame coordinate (metres, any axis) of a map point, a region's origin or a
/// camera position: UTM-size eastings and northings (< 1e7 m) pass; anything larger is an error
/// in the input, not a place. A camera_from_map's translation (−R·position) may then reach
/// √3 times this.
pub const MAX_COORDINATE_M: f64 = 1e7;

/// The largest translation entry of a camera_from_map, metres: √3 · [`MAX_COORDINATE_M`], since
/// t = −R·position.
pub const MAX_TRANSLATION_M: f64 = MAX_COORDINATE_M * 1.732_050_807_568_877_2;

/// The largest rotation entry that tolerance lets through: a column holding a larger entry has
/// a squared norm above 1 + [`ROTATION_TOLERANCE`]. Checked entry by entry, so the bound the
/// API's schema states is exactly the one applied.
pub const MAX_ROTATION_ENTRY: f64 = 1.0005;

/// How far each entry of a pose's last row may be from (0, 0, 0, 1).
pub const LAST_ROW_TOLERANCE: f64 = 1e-6;

/// The closed range of entry (row, col) of a row-major camera_from_map that
/// [`Pose::from_matrix`] accepts; the API's `Matrix4x4` schema states these very numbers.
pub fn entry_bounds(row: usize, col: usize) -> (f64, f64) {
    match (row, col) {
        (3, 3) => (1.0 - LAST_ROW_TOLERANCE, 1.0 + LAST_ROW_TOLERANCE),
        (3, _) => (-LAST_ROW_TOLERANCE, LAST_ROW_TOLERANCE),
        (_, 3) => (-MAX_TRANSLATION_M, MAX_TRANSLATION_M),
        _ => (-MAX_ROTATION_ENTRY, MAX_ROTATION_ENTRY),
    }
}

/// The JSON shape of a pose in the API and in manifests: a row-major 4x4 matrix.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct PoseMatrix(pub [[f64; 4]; 4]);

impl From<Pose> for PoseMatrix {
    fn from(p: Pose) -> Self {
        PoseMatrix(p.to_rows())
    }
}

impl TryFrom<PoseMatrix> for Pose {
    type Error = String;
    fn try_from(m: PoseMatrix) -> Result<Self, String> {
        Pose::from_matrix(&m.0)
    }
}

/// A row-major 4x4 rigid transform as JSON: 4 rows of 4 numbers. Read as nested lists so that a
/// wrong shape is a 422 naming the row, not a JSON syntax error.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Matrix4x4(pub Vec<Vec<f64>>);

impl Matrix4x4 {
    pub fn from_rows(rows: [[f64; 4]; 4]) -> Self {
        Self(rows.iter().map(|r| r.to_vec()).collect())
    }

    /// The matrix, or what is wrong with its shape.
    pub fn rows(&self) -> Result<[[f64; 4]; 4], String> {
        if self.0.len() != 4 {
            return Err(format!("must have 4 rows, has {}", self.0.len()));
        }
        let mut out = [[0.0; 4]; 4];
        for (i, row) in self.0.iter().enumerate() {
            if row.len() != 4 {
                return Err(format!("row {i} must have 4 numbers, has {}", row.len()));
            }
            out[i].copy_from_slice(row);
        }
        Ok(out)
    }

    pub fn pose(&self) -> Result<Pose, String> {
        Pose::from_matrix(&self.rows()?)
    }
}

impl utoipa::PartialSchema for Matrix4x4 {
    /// 4 rows of 4 numbers, each entry within its [`entry_bounds`] (row by row with
    /// `prefixItems`); what a JSON Schema cannot state (R orthonormal, the camera position's
    /// bound) is in the description.
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        use utoipa::openapi::schema::{ArrayBuilder, ArrayItems, ObjectBuilder, Type};
        let entry = |row: usize, col: usize| {
            let (low, high) = entry_bounds(row, col);
            ObjectBuilder::new().schema_type(Type::Number).minimum(Some(low)).maximum(Some(high)).build()
        };
        let row = |r: usize| ArrayBuilder::new().prefix_items((0..4).map(|c| entry(r, c))).items(ArrayItems::False).min_items(Some(4)).max_items(Some(4)).build();
        ArrayBuilder::new()
            .prefix_items((0..4).map(row))
            .items(ArrayItems::False)
            .min_items(Some(4))
            .max_items(Some(4))
            .description(Some(format!(
                "Row-major 4x4 rigid transform [R t; 0 0 0 1]: 4 rows of 4 numbers, each within the bounds stated per entry \
                 (rotation ±{MAX_ROTATION_ENTRY}, translation ±{MAX_TRANSLATION_M} m, last row 0 0 0 1 within ±{LAST_ROW_TOLERANCE:e}). \
                 Also refused with 422, as a JSON Schema cannot state them: R not orthonormal within {ROTATION_TOLERANCE:e} \
                 (largest entry of RᵀR − I) or with determinant < 0, and a camera position −Rᵀt beyond ±{MAX_COORDINATE_M:e} m on an axis."
            )))
            .into()
    }
}

impl utoipa::ToSchema for Matrix4x4 {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn row_major_round_trip() {
        let p = Pose::ground_motion(0.3, 1.0, -2.0).compose(&Pose::from_rt(
            Rotation3::from_euler_angles(0.1, -0.2, 0.05).into_inner(),
            Vector3::new(0.5, 0.25, -1.0),
        ));
        let back = Pose::from_row_major_3x4(&p.to_row_major_3x4()).unwrap();
        assert!((back.matrix() - p.matrix()).abs().max() < 1e-12);
        let back = Pose::from_matrix(&p.to_rows()).unwrap();
        assert!((back.matrix() - p.matrix()).abs().max() < 1e-12);
    }

    #[test]
    fn rejects_non_rigid_matrices() {
        let mut m = Pose::identity().to_rows();
        m[0][0] = 2.0;
        assert!(Pose::from_matrix(&m).is_err());
        let mut m = Pose::identity().to_rows();
        m[3][0] = 1.0;
        assert!(Pose::from_matrix(&m).is_err());
        let mut m = Pose::identity().to_rows();
        m[1][3] = f64::NAN;
        assert!(Pose::from_matrix(&m).is_err());
    }

    #[test]
    fn rotation_check_names_what_is_wrong() {
        let rig = Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0);
        assert_eq!(check_rotation(&rig), Ok(()));
        // KITTI's poses.txt keeps about 7 significant digits: still a rotation.
        let rounded = Rotation3::from_euler_angles(0.1, -0.2, 0.05).into_inner().map(|v: f64| (v * 1e6).round() / 1e6);
        assert_eq!(check_rotation(&rounded), Ok(()));
        let cases = [
            (Matrix3::zeros(), "every entry is 0"),
            (Matrix3::new(2.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), "lengths 2.0000, 1.0000, 1.0000 and RᵀR differs from the identity by up to 3.0000"),
            (Matrix3::identity() * 1.001, "tolerance 0.001"),
            (Matrix3::new(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0), "determinant is -1.0000, a reflection"),
            (Matrix3::new(f64::NAN, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), "non-finite"),
        ];
        for (m, want) in cases {
            let err = check_rotation(&m).unwrap_err();
            assert!(err.starts_with("is not a rotation: ") && err.contains(want), "{err}");
        }
        // The API's reader (which also bounds each entry, as its schema states) and the files'
        // reader accept exactly the same rotation blocks, and say "not a rotation" of the others.
        let scaled = |k: f64| rig * k;
        for r in [rig, rounded, Matrix3::identity() * 2.0, scaled(1.0004), scaled(1.0006), scaled(1.00049), Matrix3::zeros(), -rig] {
            let mut rows = Pose::identity().to_rows();
            let mut values = [0.0; 12];
            for i in 0..3 {
                for j in 0..3 {
                    rows[i][j] = r[(i, j)];
                    values[i * 4 + j] = r[(i, j)];
                }
            }
            let (api, file) = (Pose::from_matrix(&rows), Pose::from_row_major_3x4(&values));
            assert_eq!(api.is_ok(), file.is_ok(), "{r}: API {api:?}, file {file:?}");
            if let (Err(api), Err(file)) = (api, file) {
                assert!(api.starts_with("pose's rotation block is not a rotation") && file.starts_with("is not a rotation"), "{api} / {file}");
            }
        }
    }

    #[test]
    fn heading_of_a_kitti_like_rig() {
        // Camera looking along the map's +x axis: camera z = map x, camera x = -map y, camera y = -map z.
        let r = Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0);
        let rig = Pose::from_rt(r, Vector3::new(0.0, -0.08, -0.27));
        assert!(rig.camera_heading_in_map_deg().abs() < 1e-9);
        let default = Pose::level_camera_along_x(Vector3::new(1.0, 2.0, 3.0));
        assert!((default.rotation() - r).abs().max() < 1e-12 && default.camera_heading_in_map_deg().abs() < 1e-9);
        assert!((default.camera_position_in_map() - Vector3::new(1.0, 2.0, 3.0)).norm() < 1e-12);
        let turned = rig.compose(&Pose::ground_motion(-std::f64::consts::FRAC_PI_2, 0.0, 0.0));
        assert!((turned.camera_heading_in_map_deg() - 90.0).abs() < 1e-9);
    }
}
