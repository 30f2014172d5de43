//! Stateless, seedable noise: a value depends only on (seed, coordinates), never on which thread
//! computes it or in which order, so parallel rendering stays byte-identical.

/// SplitMix64 finaliser: a well-mixed 64-bit hash.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Hash of several integers.
#[inline]
pub fn hash(parts: &[u64]) -> u64 {
    parts.iter().fold(0x1234_5678_9ABC_DEF0u64, |acc, &p| mix64(acc ^ mix64(p)))
}

/// Uniform in [0, 1) from a hash.
#[inline]
pub fn unit(h: u64) -> f32 {
    (h >> 40) as f32 / (1u64 << 24) as f32
}

/// Approximately standard-normal (Box–Muller on two hashed uniforms).
#[inline]
pub fn gaussian(h: u64) -> f32 {
    let u1 = unit(h).max(1e-7);
    let u2 = unit(mix64(h));
    (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
}

/// Smooth 2-D value noise in [0, 1) with unit lattice spacing.
pub fn value_noise(seed: u64, x: f32, y: f32) -> f32 {
    let (xf, yf) = (x.floor(), y.floor());
    let (ix, iy) = (xf as i64, yf as i64);
    let (fx, fy) = (x - xf, y - yf);
    let s = |t: f32| t * t * (3.0 - 2.0 * t);
    let corner = |dx: i64, dy: i64| unit(hash(&[seed, (ix + dx) as u64, (iy + dy) as u64]));
    let (sx, sy) = (s(fx), s(fy));
    let top = corner(0, 0) * (1.0 - sx) + corner(1, 0) * sx;
    let bottom = corner(0, 1) * (1.0 - sx) + corner(1, 1) * sx;
    top * (1.0 - sy) + bottom * sy
}

/// Two octaves of value noise at scale `scale` metres.
pub fn fractal_noise(seed: u64, x: f32, y: f32, scale: f32) -> f32 {
    let a = value_noise(seed, x / scale, y / scale);
    let b = value_noise(seed ^ 0xA5A5, x * 2.7 / scale, y * 2.7 / scale);
    (a * 0.65 + b * 0.35).clamp(0.0, 1.0)
}
