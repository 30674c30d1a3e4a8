//! Lie groups used by the variables: SO(2)/SE(2) and SO(3)/SE(3); the BAL camera, 2D and 3D points.
//!
//! Layer 0: imports nothing of the crate (docs/ARCHITECTURE.md).

pub mod camera;
pub mod image;
pub mod nav_state;
pub mod preintegration;
pub mod se2;
pub mod se3;
pub mod so2;
pub mod so3;

pub use camera::{Point2, Point3, SnavelyCamera};
pub use nav_state::NavState;
pub use se2::Se2;
pub use se3::Se3;
pub use so2::{rotation_matrix_2d, wrap_angle};
