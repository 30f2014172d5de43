//! Numeric field types shared by PCD and PLY, read from bytes or from ASCII tokens.

/// One numeric type of a PCD field or a PLY property.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
}

impl Scalar {
    /// PCD spells a type as a letter (I, U, F) plus a size in bytes.
    /// The letter may be lower case (`TYPE f f f`), as PCL and Open3D accept it.
    pub(crate) fn from_pcd(kind: &str, size: usize) -> Option<Self> {
        Some(match (kind.to_ascii_uppercase().as_str(), size) {
            ("I", 1) => Scalar::I8,
            ("U", 1) => Scalar::U8,
            ("I", 2) => Scalar::I16,
            ("U", 2) => Scalar::U16,
            ("I", 4) => Scalar::I32,
            ("U", 4) => Scalar::U32,
            ("I", 8) => Scalar::I64,
            ("U", 8) => Scalar::U64,
            ("F", 4) => Scalar::F32,
            ("F", 8) => Scalar::F64,
            _ => return None,
        })
    }

    /// PLY spells a type by name, with old and new (sized) spellings.
    pub(crate) fn from_ply(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    pub(crate) fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::I64 | Scalar::U64 | Scalar::F64 => 8,
        }
    }

    /// Reads one value from the front of `bytes` (the caller guarantees `bytes.len() >= size()`).
    pub(crate) fn read(self, bytes: &[u8], big_endian: bool) -> f64 {
        macro_rules! get {
            ($t:ty, $n:expr) => {{
                let mut raw = [0u8; $n];
                raw.copy_from_slice(&bytes[..$n]);
                if big_endian { <$t>::from_be_bytes(raw) as f64 } else { <$t>::from_le_bytes(raw) as f64 }
            }};
        }
        match self {
            Scalar::I8 => bytes[0] as i8 as f64,
            Scalar::U8 => bytes[0] as f64,
            Scalar::I16 => get!(i16, 2),
            Scalar::U16 => get!(u16, 2),
            Scalar::I32 => get!(i32, 4),
            Scalar::U32 => get!(u32, 4),
            Scalar::I64 => get!(i64, 8),
            Scalar::U64 => get!(u64, 8),
            Scalar::F32 => get!(f32, 4),
            Scalar::F64 => get!(f64, 8),
        }
    }

    /// Parses one ASCII token; integers must be integers of the right sign, floats may be
    /// `nan`/`inf` (such points are dropped later, not rejected here).
    pub(crate) fn parse_ascii(self, token: &str) -> Option<f64> {
        match self {
            Scalar::F32 | Scalar::F64 => token.parse::<f64>().ok(),
            Scalar::U8 | Scalar::U16 | Scalar::U32 | Scalar::U64 => token.parse::<u64>().ok().map(|v| v as f64),
            _ => token.parse::<i64>().ok().map(|v| v as f64),
        }
    }

    /// A list length read from a PLY count property must be a non-negative integer.
    pub(crate) fn is_integer(self) -> bool {
        !matches!(self, Scalar::F32 | Scalar::F64)
    }
}
