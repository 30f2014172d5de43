//! Map regions on disk: `<id>.bin` (KITTI float32 x, y, z, intensity: the one canonical format
//! whatever was uploaded, in the region's local frame), `<id>.json` (metadata sidecar, plus the
//! server's `origin` of the local frame when it is not zero) and `<id>.emb` (cached embeddings:
//! a whole region's, or a tiled region's, see `tiles`). Every write is atomic, so a failed upload
//! leaves the previous region intact.
//!
//! The directory may be shared by several replicas (DESIGN §9): the in-memory registry is a cache
//! of the files, checked against each region's file stamps (size and modification times) on
//! every lookup, so a region another replica registered, replaced or deleted is seen at once.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, RwLock};
use std::time::SystemTime;

use serde::{Deserialize, Serialize};

use sha2::Digest;

use super::PreparedMap;
use crate::geometry::pose::PoseMatrix;
use crate::geometry::{LocalFrame, Pose};
use crate::model::manifest::sha256_hex;

use crate::atomic_file::{AtomicWriter, write_atomic};
use super::formats::{CloudFormat, PointCloud, parse};
use super::{MapError, embeddings};

/// Map ids: `^[a-z0-9][a-z0-9_-]{0,63}$`, so they are safe as file names and URL segments.
pub fn validate_id(id: &str) -> Result<(), MapError> {
    let ok = !id.is_empty()
        && id.len() <= 64
        && id.bytes().enumerate().all(|(i, b)| b.is_ascii_lowercase() || b.is_ascii_digit() || (i > 0 && (b == b'_' || b == b'-')));
    if ok { Ok(()) } else { Err(MapError::InvalidId(id.to_string())) }
}

/// What a user may attach to a region. Stored as the `<id>.json` sidecar; over HTTP it must be a
/// JSON object with only these fields ([`MapMetadata::from_json`]).
#[derive(Debug, Clone, Default, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct MapMetadata {
    /// Free text, at most 4096 characters.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(max_length = 4096)]
    pub description: Option<String>,
    /// The rig's initial camera_from_map (row-major 4x4 rigid transform: rotation, translation in
    /// metres, last row 0 0 0 1): the default prior of a localize request.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<crate::geometry::pose::Matrix4x4>)]
    pub initial_camera_from_map: Option<[[f64; 4]; 4]>,
    /// Free-form provenance: a JSON object, kept as given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Object>)]
    pub source: Option<serde_json::Value>,
}

/// The longest description, in characters (as JSON Schema's `maxLength` counts them).
pub const MAX_DESCRIPTION_CHARS: usize = 4096;

/// The fields a metadata object may have.
const METADATA_FIELDS: [&str; 3] = ["description", "initial_camera_from_map", "source"];

impl MapMetadata {
    /// Metadata from a request's JSON, checked against the schema: an object with only the known
    /// fields, each `null` or of its type (description a string, initial_camera_from_map a 4x4
    /// rigid transform, source an object), then [`MapMetadata::validate`].
    /// Errors: `MapError::BadMetadata` naming the field.
    pub fn from_json(value: serde_json::Value) -> Result<Self, MapError> {
        let bad = |m: String| MapError::BadMetadata(m);
        let serde_json::Value::Object(fields) = value else {
            return Err(bad(format!("the metadata must be a JSON object, got {}", json_kind(&value))));
        };
        if let Some(unknown) = fields.keys().find(|k| !METADATA_FIELDS.contains(&k.as_str())) {
            return Err(bad(format!("unknown field {unknown:?}; the fields are {}", METADATA_FIELDS.join(", "))));
        }
        fn field<T: serde::de::DeserializeOwned>(fields: &serde_json::Map<String, serde_json::Value>, name: &str) -> Result<Option<T>, MapError> {
            match fields.get(name) {
                None | Some(serde_json::Value::Null) => Ok(None),
                Some(v) => T::deserialize(v).map(Some).map_err(|e| MapError::BadMetadata(format!("{name}: {e}"))),
            }
        }
        let source: Option<serde_json::Value> = field(&fields, "source")?;
        if let Some(s) = source.as_ref().filter(|s| !s.is_object()) {
            return Err(bad(format!("source must be a JSON object, got {}", json_kind(s))));
        }
        let metadata = MapMetadata { description: field(&fields, "description")?, initial_camera_from_map: field(&fields, "initial_camera_from_map")?, source };
        metadata.validate()?;
        Ok(metadata)
    }

    /// A stored sidecar: fields this version does not know (written by a newer replica sharing
    /// the directory) are ignored rather than making the region unreadable.
    pub fn from_sidecar(text: &[u8]) -> Result<Self, serde_json::Error> {
        let mut value: serde_json::Value = serde_json::from_slice(text)?;
        if let Some(fields) = value.as_object_mut() {
            fields.retain(|k, _| METADATA_FIELDS.contains(&k.as_str()));
        }
        serde_json::from_value(value)
    }

    /// The checks the types do not make: description length, the matrix is a finite rigid
    /// transform. (Not the type of `source`, so sidecars written before it was checked still load.)
    /// Errors: `MapError::BadMetadata`.
    pub fn validate(&self) -> Result<(), MapError> {
        if let Some(m) = self.initial_camera_from_map {
            Pose::try_from(PoseMatrix(m)).map_err(|e| MapError::BadMetadata(format!("initial_camera_from_map: {e}")))?;
        }
        if self.description.as_ref().is_some_and(|d| d.chars().count() > MAX_DESCRIPTION_CHARS) {
            return Err(MapError::BadMetadata(format!("description is longer than {MAX_DESCRIPTION_CHARS} characters")));
        }
        Ok(())
    }

    pub fn initial_pose(&self) -> Option<Pose> {
        self.initial_camera_from_map.and_then(|m| Pose::try_from(PoseMatrix(m)).ok())
    }
}

/// The axis-aligned box holding a region's points, map frame, metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Extent {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

impl Extent {
    /// The box of `points` (local frame) in the map frame; `None` for no points.
    pub fn of(points: &[[f32; 3]], frame: LocalFrame) -> Option<Self> {
        let mut min = [f64::INFINITY; 3];
        let mut max = [f64::NEG_INFINITY; 3];
        for p in points {
            for c in 0..3 {
                min[c] = min[c].min(p[c] as f64);
                max[c] = max[c].max(p[c] as f64);
            }
        }
        (!points.is_empty()).then(|| Extent { min: frame.point_to_map([min[0] as f32, min[1] as f32, min[2] as f32]), max: frame.point_to_map([max[0] as f32, max[1] as f32, max[2] as f32]) })
    }

    /// Whether the ground-plane position (x, y) lies inside the box's x-y rectangle.
    pub fn contains_xy(&self, x: f64, y: f64) -> bool {
        (self.min[0]..=self.max[0]).contains(&x) && (self.min[1]..=self.max[1]).contains(&y)
    }
}

impl std::fmt::Display for Extent {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "x {:.2}..{:.2}, y {:.2}..{:.2}, z {:.2}..{:.2} m", self.min[0], self.max[0], self.min[1], self.max[1], self.min[2], self.max[2])
    }
}

/// One stored region, as listed by the API.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct MapEntry {
    pub id: String,
    /// Finite points in the stored cloud.
    pub num_points: usize,
    pub file_bytes: u64,
    /// sha256 of `<id>.bin`.
    pub source_sha256: String,
    pub metadata: MapMetadata,
    /// Map-frame coordinates (float64, metres) of the local frame the points are stored in:
    /// p_map = p_stored + origin.
    pub origin: [f64; 3],
    /// The box of the stored points, map frame.
    pub extent: Extent,
}

impl MapEntry {
    pub fn frame(&self) -> LocalFrame {
        LocalFrame { origin: self.origin.into() }
    }
}

/// A region's cloud written to a temp file (not yet in place), by [`MapStore::stage`].
pub struct Staged {
    bin: AtomicWriter,
    sha256: String,
    file_bytes: u64,
    num_points: usize,
    frame: LocalFrame,
    extent: Extent,
}

impl Staged {
    /// sha256 of the `<id>.bin` it will become (what embeddings files name as their source).
    pub fn sha256(&self) -> &str {
        &self.sha256
    }
}

/// The sidecar's text: the metadata, plus `origin` when the local frame is not the map frame.
fn sidecar_bytes(metadata: &MapMetadata, origin: [f64; 3]) -> Vec<u8> {
    let mut value = serde_json::to_value(metadata).expect("metadata serialises");
    if origin != [0.0; 3] {
        if let Some(fields) = value.as_object_mut() {
            fields.insert("origin".into(), serde_json::json!(origin));
        }
    }
    serde_json::to_vec_pretty(&value).expect("sidecar serialises")
}

/// The `origin` a sidecar records (zero when absent). Errors: not three finite numbers within
/// the coordinate bound.
fn sidecar_origin(text: &[u8]) -> Result<[f64; 3], String> {
    let value: serde_json::Value = serde_json::from_slice(text).map_err(|e| e.to_string())?;
    match value.get("origin") {
        None | Some(serde_json::Value::Null) => Ok([0.0; 3]),
        Some(v) => {
            let origin: [f64; 3] = serde_json::from_value(v.clone()).map_err(|e| format!("origin: {e}"))?;
            LocalFrame::new(origin).map(|f| f.origin())
        }
    }
}

/// What changes when any replica rewrites a region: `<id>.bin` (size, mtime) and `<id>.json` (mtime).
/// Atomic writes replace the file, so a rewrite always moves the modification time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Stamp {
    bin: (u64, SystemTime),
    json: Option<SystemTime>,
}

pub struct MapStore {
    dir: PathBuf,
    registry: RwLock<BTreeMap<String, (MapEntry, Stamp)>>,
    /// Serialises writers so two uploads of one id cannot interleave their files.
    writes: Mutex<()>,
}

impl MapStore {
    /// Opens (creating if needed) a map directory and registers every valid `<id>.bin` in it.
    /// Files that cannot be read are reported in the returned warnings and skipped.
    pub fn open(dir: &Path) -> Result<(Self, Vec<String>), MapError> {
        std::fs::create_dir_all(dir).map_err(|e| MapError::Io(format!("cannot create {}: {e}", dir.display())))?;
        let store = MapStore { dir: dir.to_path_buf(), registry: RwLock::new(BTreeMap::new()), writes: Mutex::new(()) };
        let mut warnings = Vec::new();
        crate::atomic_file::remove_orphaned_temp_files(dir);
        let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(|e| MapError::Io(format!("cannot list {}: {e}", dir.display())))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "bin"))
            .collect();
        entries.sort();
        for path in entries {
            let Some(id) = path.file_stem().and_then(|s| s.to_str()).map(str::to_string) else { continue };
            if validate_id(&id).is_err() {
                warnings.push(format!("{}: not a valid map id, skipped", path.display()));
                continue;
            }
            if let Err(e) = store.get(&id) {
                warnings.push(format!("{}: {e}; skipped", path.display()));
            }
        }
        Ok((store, warnings))
    }

    fn path(&self, id: &str, ext: &str) -> PathBuf {
        self.dir.join(format!("{id}.{ext}"))
    }

    fn load_entry(&self, id: &str) -> Result<MapEntry, MapError> {
        let (cloud, sha, bytes) = self.read_cloud(id)?;
        let (metadata, origin) = match std::fs::read(self.path(id, "json")) {
            Ok(text) => {
                let m = MapMetadata::from_sidecar(&text).map_err(|e| MapError::BadMetadata(format!("{id}.json: {e}")))?;
                m.validate()?;
                let origin = sidecar_origin(&text).map_err(|e| MapError::BadMetadata(format!("{id}.json: {e}")))?;
                (m, origin)
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => (MapMetadata::default(), [0.0; 3]),
            Err(e) => return Err(MapError::Io(format!("{id}.json: {e}"))),
        };
        let frame = LocalFrame { origin: origin.into() };
        let extent = Extent::of(&cloud.xyz, frame).ok_or_else(|| MapError::BadCloud(format!("{id}.bin has no points")))?;
        Ok(MapEntry { id: id.to_string(), num_points: cloud.len(), file_bytes: bytes, source_sha256: sha, metadata, origin, extent })
    }

    /// The stored cloud (points and intensity: 0 where the upload had none) and the sha256 and
    /// size of its file.
    pub fn read_cloud(&self, id: &str) -> Result<(PointCloud, String, u64), MapError> {
        let path = self.path(id, "bin");
        let bytes = std::fs::read(&path).map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => MapError::NotFound(id.to_string()),
            _ => MapError::Io(format!("{}: {e}", path.display())),
        })?;
        let cloud = parse(&bytes, CloudFormat::KittiBin).map_err(|e| MapError::BadCloud(format!("{}: {e}", path.display())))?;
        Ok((cloud, sha256_hex(&bytes), bytes.len() as u64))
    }

    fn stamp(&self, id: &str) -> Option<Stamp> {
        let bin = std::fs::metadata(self.path(id, "bin")).ok()?;
        let json = std::fs::metadata(self.path(id, "json")).and_then(|m| m.modified()).ok();
        Some(Stamp { bin: (bin.len(), bin.modified().ok()?), json })
    }

    /// The region as the files say now: re-reads a region whose stamp moved since it was
    /// registered (or one registered by another replica), forgets one whose files are gone.
    pub fn get(&self, id: &str) -> Result<MapEntry, MapError> {
        validate_id(id)?;
        let Some(stamp) = self.stamp(id) else {
            self.registry.write().expect("registry").remove(id);
            return Err(MapError::NotFound(id.to_string()));
        };
        if let Some((entry, seen)) = self.registry.read().expect("registry").get(id) {
            if *seen == stamp {
                return Ok(entry.clone());
            }
        }
        let entry = self.load_entry(id)?;
        self.registry.write().expect("registry").insert(id.to_string(), (entry.clone(), stamp));
        Ok(entry)
    }

    /// Every region in the directory (including those other replicas added), by id.
    pub fn list(&self) -> Vec<MapEntry> {
        let mut ids: std::collections::BTreeSet<String> = self.ids().into_iter().collect();
        ids.extend(self.registry.read().expect("registry").keys().cloned());
        ids.iter().filter_map(|id| self.get(id).ok()).collect()
    }

    /// The ids of the `<id>.bin` files in the directory now, sorted, without reading them (a
    /// file that would not load is named too; [`MapStore::list`] reads and checks each).
    pub fn ids(&self) -> Vec<String> {
        let mut ids: Vec<String> = std::fs::read_dir(&self.dir)
            .map(|rd| {
                rd.filter_map(|e| e.ok())
                    .filter_map(|e| e.file_name().to_str().and_then(|n| n.strip_suffix(".bin")).map(str::to_string))
                    .filter(|id| validate_id(id).is_ok())
                    .collect()
            })
            .unwrap_or_default();
        ids.sort();
        ids
    }

    /// The directory the store reads and writes.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn register(&self, id: &str, entry: &MapEntry) {
        if let Some(stamp) = self.stamp(id) {
            self.registry.write().expect("registry").insert(id.to_string(), (entry.clone(), stamp));
        }
    }

    /// Writes `cloud` (points in `frame`) as `<id>.bin` to a temp file, hashing it as it goes;
    /// nothing is in place until [`MapStore::commit`].
    pub fn stage(&self, id: &str, cloud: &PointCloud, frame: LocalFrame) -> Result<Staged, MapError> {
        validate_id(id)?;
        let io = |e: std::io::Error| MapError::Io(e.to_string());
        let extent = Extent::of(&cloud.xyz, frame).ok_or_else(|| MapError::BadCloud("the cloud has no points".into()))?;
        let mut bin = AtomicWriter::create(&self.path(id, "bin")).map_err(io)?;
        let mut hasher = sha2::Sha256::new();
        let mut record = [0u8; 16];
        for (i, p) in cloud.xyz.iter().enumerate() {
            let intensity = cloud.intensity.as_ref().and_then(|v| v.get(i).copied()).unwrap_or(0.0);
            for (k, value) in [p[0], p[1], p[2], intensity].into_iter().enumerate() {
                record[4 * k..4 * k + 4].copy_from_slice(&value.to_le_bytes());
            }
            hasher.update(record);
            bin.write_all(&record).map_err(io)?;
        }
        let sha256 = hasher.finalize().iter().map(|b| format!("{b:02x}")).collect();
        Ok(Staged { bin, sha256, file_bytes: cloud.xyz.len() as u64 * 16, num_points: cloud.xyz.len(), frame, extent })
    }

    /// A temp file that becomes `<id>.emb` on [`MapStore::commit`].
    pub fn stage_embeddings(&self, id: &str) -> Result<AtomicWriter, MapError> {
        validate_id(id)?;
        AtomicWriter::create(&self.path(id, "emb")).map_err(|e| MapError::Io(e.to_string()))
    }

    /// Puts a staged region in place: cloud, embeddings when given, then metadata (each an atomic
    /// rename or write, fsynced), then registers it. `metadata: None` keeps an existing region's
    /// metadata. A whole region's embeddings come later, by [`MapStore::save_embeddings`].
    pub fn commit(&self, id: &str, staged: Staged, embeddings: Option<AtomicWriter>, metadata: Option<MapMetadata>) -> Result<MapEntry, MapError> {
        validate_id(id)?;
        let _guard = self.writes.lock().expect("writes");
        let metadata = match metadata {
            Some(m) => m,
            None => self.get(id).map(|e| e.metadata).unwrap_or_default(),
        };
        let io = |e: std::io::Error| MapError::Io(e.to_string());
        let origin = staged.frame.origin();
        staged.bin.commit().map_err(io)?;
        if let Some(embeddings) = embeddings {
            embeddings.commit().map_err(io)?;
        }
        write_atomic(&self.path(id, "json"), &sidecar_bytes(&metadata, origin)).map_err(io)?;
        let entry = MapEntry {
            id: id.to_string(),
            num_points: staged.num_points,
            file_bytes: staged.file_bytes,
            source_sha256: staged.sha256,
            metadata,
            origin,
            extent: staged.extent,
        };
        self.register(id, &entry);
        Ok(entry)
    }

    /// Stores a whole region (points in the map frame) with its prepared embeddings: stage,
    /// embeddings, commit.
    pub fn put(
        &self,
        id: &str,
        cloud: &PointCloud,
        metadata: Option<MapMetadata>,
        prepared: &PreparedMap,
        model_sha: &str,
    ) -> Result<MapEntry, MapError> {
        let staged = self.stage(id, cloud, LocalFrame::default())?;
        let mut emb = self.stage_embeddings(id)?;
        embeddings::write(&mut emb, prepared, model_sha, staged.sha256()).map_err(|e| MapError::Io(e.to_string()))?;
        self.commit(id, staged, Some(emb), metadata)
    }

    pub fn set_metadata(&self, id: &str, metadata: MapMetadata) -> Result<MapEntry, MapError> {
        metadata.validate()?;
        let _guard = self.writes.lock().expect("writes");
        let mut entry = self.get(id)?;
        write_atomic(&self.path(id, "json"), &sidecar_bytes(&metadata, entry.origin)).map_err(|e| MapError::Io(e.to_string()))?;
        entry.metadata = metadata;
        self.register(id, &entry);
        Ok(entry)
    }

    pub fn delete(&self, id: &str) -> Result<(), MapError> {
        validate_id(id)?;
        let _guard = self.writes.lock().expect("writes");
        let known = self.registry.write().expect("registry").remove(id).is_some();
        if !known && self.stamp(id).is_none() {
            return Err(MapError::NotFound(id.to_string()));
        }
        for ext in ["bin", "emb", "json"] {
            match std::fs::remove_file(self.path(id, ext)) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => return Err(MapError::Io(e.to_string())),
            }
        }
        Ok(())
    }

    /// The persisted embeddings of a whole region, when they match this model and the stored
    /// cloud.
    pub fn load_embeddings(&self, id: &str, model_sha: &str, source_sha: &str) -> Option<PreparedMap> {
        let bytes = std::fs::read(self.path(id, "emb")).ok()?;
        embeddings::decode(&bytes, model_sha, source_sha)
    }

    /// The persisted tiles of a large region, memory-mapped, when they match this model, the
    /// stored cloud and `config`, hold embeddings when `embeddings` (a file of points alone
    /// serves a server that encodes its crops), and each point's intensity when `intensity` (a
    /// model that reads it).
    pub fn load_tiles(&self, id: &str, model_sha: &str, source_sha: &str, config: super::tiles::TileConfig, embeddings: bool, intensity: bool) -> Option<super::tiles::TiledMap> {
        let path = self.path(id, "emb");
        if !path.exists() {
            return None; // not written yet (`map build --store` leaves it to the first reader)
        }
        match super::tiles::TiledMap::open(&path, model_sha, source_sha) {
            Ok(Some(t)) if t.config == config && (t.d > 0 || !embeddings) && (t.has_intensity() || !intensity) => Some(t),
            Ok(_) => None,
            Err(e) => {
                tracing::warn!("{id}.emb: {e:#}; recomputing");
                None
            }
        }
    }

    /// What `<id>.emb` holds, from its header: (file bytes, tiled cell count or `None` for a
    /// whole region's file). `None` when there is no file.
    pub fn embeddings_file(&self, id: &str) -> Option<(u64, Option<usize>)> {
        use std::io::Read;
        let mut file = std::fs::File::open(self.path(id, "emb")).ok()?;
        let len = file.metadata().ok()?.len();
        let mut head = vec![0u8; super::tiles::HEADER_BYTES];
        let read = file.read(&mut head).ok()?;
        Some((len, super::tiles::header_cells(&head[..read])))
    }

    /// Writes a whole region's `<id>.emb`: written and fsynced outside the store's write lock,
    /// then renamed into place under it, only while the registered cloud of `id` is still
    /// `source_sha`. `Ok(false)`, nothing written, when the region was replaced or deleted
    /// meanwhile (the file would name a cloud no longer stored).
    pub fn save_embeddings(&self, id: &str, prepared: &PreparedMap, model_sha: &str, source_sha: &str) -> Result<bool, MapError> {
        let io = |e: std::io::Error| MapError::Io(e.to_string());
        let mut emb = self.stage_embeddings(id)?;
        embeddings::write(&mut emb, prepared, model_sha, source_sha).map_err(io)?;
        emb.sync().map_err(io)?;
        let _guard = self.writes.lock().expect("writes");
        let current = self.registry.read().expect("registry").get(id).map(|(e, _)| e.source_sha256 == source_sha);
        if current != Some(true) {
            return Ok(false);
        }
        emb.commit().map_err(io)?;
        Ok(true)
    }
}

fn json_kind(value: &serde_json::Value) -> &'static str {
    match value {
        serde_json::Value::Null => "null",
        serde_json::Value::Bool(_) => "a boolean",
        serde_json::Value::Number(_) => "a number",
        serde_json::Value::String(_) => "a string",
        serde_json::Value::Array(_) => "an array",
        serde_json::Value::Object(_) => "an object",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn opening_removes_stale_temp_files_and_skips_bad_names() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join(".a.bin.tmp-1-0"), b"half").unwrap();
        std::fs::write(dir.path().join("Bad.bin"), [0u8; 16]).unwrap();
        std::fs::write(dir.path().join("broken.bin"), [0u8; 5]).unwrap();
        std::fs::write(dir.path().join("ok.bin"), [0u8; 32]).unwrap();
        let (store, warnings) = MapStore::open(dir.path()).unwrap();
        assert!(!dir.path().join(".a.bin.tmp-1-0").exists());
        assert_eq!(store.list().iter().map(|e| e.id.as_str()).collect::<Vec<_>>(), ["ok"]);
        assert_eq!(warnings.len(), 2, "{warnings:?}");
    }

    #[test]
    fn opening_spares_a_temp_file_that_a_live_writer_holds() {
        let dir = tempfile::tempdir().unwrap();
        let live = dir.path().join(".yard.bin.tmp-7-0-0badc0de");
        let held = std::fs::File::create(&live).unwrap();
        held.lock().unwrap(); // as another replica's write_atomic holds it
        let orphan = dir.path().join(".yard.emb.tmp-7-1-0badc0de");
        std::fs::write(&orphan, b"left by a kill -9").unwrap();
        MapStore::open(dir.path()).unwrap();
        assert!(live.exists(), "another replica's upload in progress survives a store opening");
        assert!(!orphan.exists());
        drop(held);
        MapStore::open(dir.path()).unwrap();
        assert!(!live.exists(), "swept once its writer is gone");
    }

    #[test]
    fn a_sidecar_with_fields_from_a_newer_version_still_loads() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("ok.bin"), [0u8; 32]).unwrap();
        std::fs::write(dir.path().join("ok.json"), br#"{"description": "d", "source": 5, "added_later": true}"#).unwrap();
        let (store, warnings) = MapStore::open(dir.path()).unwrap();
        assert!(warnings.is_empty(), "{warnings:?}");
        assert_eq!(store.get("ok").unwrap().metadata.description.as_deref(), Some("d"));
    }

    #[test]
    fn metadata_from_json_follows_the_schema() {
        let ok = MapMetadata::from_json(serde_json::json!({"description": "d", "source": {"by": "lidar"}, "initial_camera_from_map": null})).unwrap();
        assert_eq!(ok.description.as_deref(), Some("d"));
        assert!(ok.initial_camera_from_map.is_none());
        for (bad, says) in [
            (serde_json::json!({"source": 5}), "source must be a JSON object, got a number"),
            (serde_json::json!({"source": "x"}), "source must be a JSON object, got a string"),
            (serde_json::json!({"description": 5}), "description:"),
            (serde_json::json!({"initial_camera_from_map": [[1, 0, 0, 0]]}), "initial_camera_from_map:"),
            (serde_json::json!({"initial_camera_from_map": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}), "initial_camera_from_map:"),
            (serde_json::json!({"descripton": "typo"}), "unknown field \"descripton\""),
            (serde_json::json!(["d", null, null]), "must be a JSON object, got an array"),
            (serde_json::json!({"description": "x".repeat(4097)}), "longer than 4096"),
        ] {
            let err = MapMetadata::from_json(bad.clone()).unwrap_err().to_string();
            assert!(err.contains(says), "{bad}: {err}");
        }
    }

    #[test]
    fn replicas_sharing_a_directory_see_each_others_changes() {
        use crate::maps::formats::PointCloud;
        let dir = tempfile::tempdir().unwrap();
        let (a, _) = MapStore::open(dir.path()).unwrap();
        let (b, _) = MapStore::open(dir.path()).unwrap();
        let cloud = |n: usize| PointCloud { xyz: (0..n).map(|i| [i as f32, 1.0, -1.0]).collect(), intensity: None };
        let prepared = PreparedMap { points: vec![[0.0; 3]], features: vec![0.0; 64], pivot: nalgebra::Point3::origin(), source_points: 1, intensity: None };
        assert!(matches!(b.get("yard"), Err(MapError::NotFound(_))));

        a.put("yard", &cloud(10), None, &prepared, "model").unwrap();
        let first = b.get("yard").unwrap();
        assert_eq!(first.num_points, 10, "registered by the other replica");
        assert_eq!(b.list().len(), 1);

        std::thread::sleep(std::time::Duration::from_millis(20)); // a distinct mtime on coarse clocks
        a.put("yard", &cloud(12), None, &prepared, "model").unwrap();
        let entry = b.get("yard").unwrap();
        assert_eq!(entry.num_points, 12, "replaced by the other replica");
        assert_ne!(entry.source_sha256, first.source_sha256);

        let mut meta = MapMetadata::default();
        meta.description = Some("moved".into());
        std::thread::sleep(std::time::Duration::from_millis(20));
        b.set_metadata("yard", meta).unwrap();
        assert_eq!(a.get("yard").unwrap().metadata.description.as_deref(), Some("moved"));

        a.delete("yard").unwrap();
        assert!(matches!(b.get("yard"), Err(MapError::NotFound(_))));
        assert!(b.list().is_empty());
    }

    #[test]
    fn embeddings_for_a_replaced_or_deleted_region_are_not_written() {
        use crate::maps::formats::PointCloud;
        let dir = tempfile::tempdir().unwrap();
        let (store, _) = MapStore::open(dir.path()).unwrap();
        let cloud = |n: usize| PointCloud { xyz: (0..n).map(|i| [i as f32, 1.0, -1.0]).collect(), intensity: None };
        let prepared = PreparedMap { points: vec![[0.5; 3]], features: vec![0.25; 64], pivot: nalgebra::Point3::origin(), source_points: 1, intensity: None };
        let emb = dir.path().join("yard.emb");
        let staged = store.stage("yard", &cloud(10), LocalFrame::default()).unwrap();
        let first = store.commit("yard", staged, None, None).unwrap();
        assert!(!emb.exists(), "a whole region's embeddings come separately");
        assert!(store.save_embeddings("yard", &prepared, "model", &first.source_sha256).unwrap());
        assert!(store.load_embeddings("yard", "model", &first.source_sha256).is_some());

        let staged = store.stage("yard", &cloud(12), LocalFrame::default()).unwrap();
        let second = store.commit("yard", staged, None, None).unwrap();
        let on_disk = std::fs::read(&emb).unwrap();
        assert!(!store.save_embeddings("yard", &prepared, "model", &first.source_sha256).unwrap(), "a late write for the replaced cloud");
        assert_eq!(std::fs::read(&emb).unwrap(), on_disk);
        assert!(store.save_embeddings("yard", &prepared, "model", &second.source_sha256).unwrap());

        store.delete("yard").unwrap();
        assert!(!store.save_embeddings("yard", &prepared, "model", &second.source_sha256).unwrap(), "a late write for a deleted region");
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert!(left.is_empty(), "no file, temp or final, is left: {left:?}");
    }

    #[test]
    fn ids() {
        for ok in ["demo", "a", "kitti_00-12", &"a".repeat(64)] {
            assert!(validate_id(ok).is_ok(), "{ok}");
        }
        for bad in ["", "-a", "_a", "A", "a/b", "..", "a.b", &"a".repeat(65), "é"] {
            assert!(validate_id(bad).is_err(), "{bad}");
        }
    }
}
