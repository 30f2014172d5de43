//! PLACEHOLDER until the formats branch is merged (take that branch's version of this file):
//! the same API (`CloudFormat`, `PointCloud`, `parse`, `CloudFormat::sniff`), KITTI `.bin` only.

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CloudFormat {
    KittiBin,
    Pcd,
    Ply,
}

impl CloudFormat {
    pub fn sniff(bytes: &[u8]) -> Option<CloudFormat> {
        if bytes.starts_with(b"ply") {
            Some(CloudFormat::Ply)
        } else if bytes.starts_with(b"# .PCD") || bytes.starts_with(b"VERSION") || bytes.starts_with(b"FIELDS") {
            Some(CloudFormat::Pcd)
        } else if !bytes.is_empty() && bytes.len() % 16 == 0 {
            Some(CloudFormat::KittiBin)
        } else {
            None
        }
    }
}

#[derive(Debug, Clone, Default)]
pub struct PointCloud {
    pub xyz: Vec<[f32; 3]>,
    pub intensity: Option<Vec<f32>>,
}

#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct FormatError(pub String);

pub fn parse(bytes: &[u8], format: CloudFormat) -> Result<PointCloud, FormatError> {
    match format {
        CloudFormat::KittiBin => {
            if bytes.is_empty() || bytes.len() % 16 != 0 {
                return Err(FormatError(format!("KITTI .bin size {} is not a positive multiple of 16 bytes", bytes.len())));
            }
            let mut xyz = Vec::with_capacity(bytes.len() / 16);
            let mut intensity = Vec::with_capacity(bytes.len() / 16);
            for rec in bytes.chunks_exact(16) {
                let f = |i: usize| f32::from_le_bytes(rec[i * 4..i * 4 + 4].try_into().unwrap());
                let p = [f(0), f(1), f(2)];
                if p.iter().all(|v| v.is_finite()) {
                    xyz.push(p);
                    intensity.push(f(3));
                }
            }
            if xyz.is_empty() {
                return Err(FormatError("no finite points".into()));
            }
            Ok(PointCloud { xyz, intensity: Some(intensity) })
        }
        other => Err(FormatError(format!("{other:?} is not supported by this build"))),
    }
}
