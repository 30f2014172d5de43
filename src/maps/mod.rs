//! Map regions: point-cloud file formats (more to come: store, cache).

pub mod formats;
