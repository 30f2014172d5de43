//! The project's one home for geometry conventions.
//!
//! Every other part (generator, readers, server, evaluator) and the Python training pipeline
//! follow what is written here; `fixtures/conventions.json` pins these functions across languages.
//!
//! Frames:
//! - camera: OpenCV (x right, y down, z forward); pixel (u, v) = (fx x/z + cx, fy y/z + cy) with
//!   pixel centres at integer coordinates;
//! - map: the region's own frame, z up (a LiDAR frame such as KITTI's velodyne frame);
//! - local: the map frame moved to the region's origin (`frame`): what stored points, the cache
//!   and the agent use, so float32 keeps its precision at UTM-size coordinates;
//! - the estimated quantity is `camera_from_map`: p_cam = R p_map + t.

pub mod actions;
pub mod camera;
pub mod frame;
pub mod metrics;
pub mod pose;
pub mod voxel;

pub use actions::{ActionFrame, ActionSet, AgentAction, Dof};
pub use camera::{CropAnchor, Intrinsics, MIN_DEPTH_M, PreprocessPlan, input_scale, max_input_scale};
pub use frame::LocalFrame;
pub use metrics::{PoseError, p2p_distance, step_reward};
pub use pose::{MAX_COORDINATE_M, Pose, ROTATION_TOLERANCE, check_rotation};
