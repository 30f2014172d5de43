//! Ground that is not flat: a road whose centreline curves (y = c(x)), whose surface climbs and
//! falls (z = p(x)) and banks (cross slope b(x)), with a cross-section around it: an optional
//! kerb, ditches, and side slopes that rise (cuttings, embankments beside the road) or fall (a
//! road on an embankment). Junctions flatten the roadside.
//!
//! Scene frame: z up, x along the road's general direction. Lateral road coordinate
//! ŷ = y − c(x) (a shear, close to the distance from the centreline for gentle curves).
//! The height h(x, y) is a smooth function; rays meet it by a secant march with bracketing.

use serde::Serialize;

use super::shapes::V3;

/// A sum of sines a·sin(2πx/λ + φ): each term is [a, λ, φ] (metres, metres, radians).
pub type Waves = [[f32; 3]; 2];

fn waves(w: &Waves, x: f32) -> f32 {
    w.iter().map(|[a, l, p]| a * (std::f32::consts::TAU * x / l + p).sin()).sum()
}

fn smooth01(t: f32) -> f32 {
    let t = t.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// One side of the road's cross-section, distances measured outwards from the road's edge.
#[derive(Debug, Clone, Copy, Serialize, Default)]
pub struct Roadside {
    /// Ditch: starts `ditch_start_m` out, `ditch_width_m` wide, `ditch_depth_m` deep (0 = none).
    pub ditch_start_m: f32,
    pub ditch_width_m: f32,
    pub ditch_depth_m: f32,
    /// Side slope: from `slope_start_m` out over `slope_width_m`, the ground rises by
    /// `slope_rise_m` (negative: falls away, the road runs on an embankment).
    pub slope_start_m: f32,
    pub slope_width_m: f32,
    pub slope_rise_m: f32,
}

/// The road's shape; everything is in metres, slopes as tangents.
#[derive(Debug, Clone, Serialize)]
pub struct RoadShape {
    pub curve: Waves,
    pub profile: Waves,
    /// Cross slope: mean + one wave (tangent; 0.05 ≈ 2.9°), positive = left side higher.
    pub bank_mean: f32,
    pub bank_wave: [f32; 3],
    /// Half width of the banked carriageway.
    pub road_half_width_m: f32,
    /// Kerb height at the carriageway's edge (0 = no kerb).
    pub kerb_m: f32,
    /// [left (+y), right (−y)].
    pub sides: [Roadside; 2],
    /// Junctions (x centre, half width): kerbs, ditches and side slopes fade out there.
    pub junctions: Vec<(f32, f32)>,
}

impl RoadShape {
    /// Flat, straight, no kerb: the ground plane z = 0 as a road shape.
    pub fn flat(road_half_width_m: f32) -> Self {
        RoadShape {
            curve: [[0.0, 100.0, 0.0]; 2],
            profile: [[0.0, 100.0, 0.0]; 2],
            bank_mean: 0.0,
            bank_wave: [0.0, 100.0, 0.0],
            road_half_width_m,
            kerb_m: 0.0,
            sides: [Roadside::default(); 2],
            junctions: Vec::new(),
        }
    }
}

const TABLE_STEP_M: f32 = 0.5;

/// A road shape tabulated along x (centreline, its slope, height, bank, junction mask) so a
/// height query is a few multiplications.
#[derive(Debug, Clone)]
pub struct Terrain {
    pub shape: RoadShape,
    x0: f32,
    /// [c, c', p, bank, junction mask] every `TABLE_STEP_M`.
    table: Vec<[f32; 5]>,
    z_min: f32,
    /// Largest |d²c/dx²| of the centreline (1/m).
    curvature: f32,
    /// Highest ground over all x ≥ (ahead) and ≤ (behind) each table row: a ray climbing
    /// above it can no longer meet the ground.
    max_ahead: Vec<f32>,
    max_behind: Vec<f32>,
}

/// Values along x at one point.
#[derive(Debug, Clone, Copy)]
pub struct Along {
    /// Centreline y and its slope dc/dx.
    pub centre: f32,
    pub centre_slope: f32,
    /// Carriageway height on the centreline.
    pub height: f32,
    pub bank: f32,
    /// 1 inside a junction, 0 away from it.
    pub junction: f32,
}

impl Terrain {
    /// Tabulates `shape` over x in [x0, x1] (queries outside use the end values).
    pub fn new(shape: RoadShape, x0: f32, x1: f32) -> Self {
        let n = ((x1 - x0) / TABLE_STEP_M).ceil() as usize + 2;
        let table: Vec<[f32; 5]> = (0..n)
            .map(|i| {
                let x = x0 + i as f32 * TABLE_STEP_M;
                let e = 0.01;
                let slope = (waves(&shape.curve, x + e) - waves(&shape.curve, x - e)) / (2.0 * e);
                let [a, l, p] = shape.bank_wave;
                let bank = shape.bank_mean + a * (std::f32::consts::TAU * x / l + p).sin();
                let junction = shape
                    .junctions
                    .iter()
                    .map(|&(cx, hw)| 1.0 - smooth01(((x - cx).abs() - hw) / 4.0))
                    .fold(0.0f32, f32::max);
                [waves(&shape.curve, x), slope, waves(&shape.profile, x), bank, junction]
            })
            .collect();
        let lo = table.iter().fold(f32::INFINITY, |lo, r| lo.min(r[2]));
        let bank_max = shape.bank_mean.abs() + shape.bank_wave[0].abs();
        let tilt = bank_max * shape.road_half_width_m;
        let up = shape.sides.iter().map(|s| s.slope_rise_m.max(0.0)).fold(0.0, f32::max) + shape.kerb_m;
        let down = shape.sides.iter().map(|s| s.ditch_depth_m + (-s.slope_rise_m).max(0.0)).fold(0.0, f32::max);
        let curvature = table.windows(2).map(|w| (w[1][1] - w[0][1]).abs() / TABLE_STEP_M).fold(0.0f32, f32::max) * 1.1 + 1e-6;
        let top: Vec<f32> = table.iter().map(|r| r[2] + tilt + up + 0.01).collect();
        let mut max_ahead = top.clone();
        for i in (0..top.len().saturating_sub(1)).rev() {
            max_ahead[i] = max_ahead[i].max(max_ahead[i + 1]);
        }
        let mut max_behind = top;
        for i in 1..max_behind.len() {
            max_behind[i] = max_behind[i].max(max_behind[i - 1]);
        }
        Terrain { shape, x0, table, z_min: lo - tilt - down - 0.01, curvature, max_ahead, max_behind }
    }

    /// The highest the ground gets from x onwards in the direction of `dx`'s sign.
    fn max_towards(&self, x: f32, dx: f32) -> f32 {
        let f = ((x - self.x0) / TABLE_STEP_M).clamp(0.0, (self.table.len() - 1) as f32);
        if dx >= 0.0 { self.max_ahead[f.floor() as usize] } else { self.max_behind[f.ceil() as usize] }
    }

    /// Table row and fraction at x (queries outside the table use its ends).
    #[inline]
    fn row(&self, x: f32) -> (usize, f32) {
        let f = ((x - self.x0) / TABLE_STEP_M).clamp(0.0, (self.table.len() - 2) as f32);
        // f ≥ 0, so truncation is floor (and avoids a libm call).
        let i = (f as usize).min(self.table.len() - 2);
        (i, f - i as f32)
    }

    /// Road values at x.
    pub fn along(&self, x: f32) -> Along {
        let (i, t) = self.row(x);
        let (a, b) = (&self.table[i], &self.table[i + 1]);
        let l = |k: usize| a[k] + (b[k] - a[k]) * t;
        Along { centre: l(0), centre_slope: l(1), height: l(2), bank: l(3), junction: l(4) }
    }

    /// Ground height at scene (x, y).
    #[inline]
    pub fn height(&self, x: f32, y: f32) -> f32 {
        let (i, t) = self.row(x);
        let (a, b) = (&self.table[i], &self.table[i + 1]);
        let l = |k: usize| a[k] + (b[k] - a[k]) * t;
        let along = Along { centre: l(0), centre_slope: 0.0, height: l(2), bank: l(3), junction: l(4) };
        along.height + self.cross(y - along.centre, &along)
    }

    /// Height of the cross-section above the centreline at lateral position `yh`.
    #[inline]
    fn cross(&self, yh: f32, a: &Along) -> f32 {
        let s = &self.shape;
        let rw = s.road_half_width_m;
        let mut z = a.bank * yh.clamp(-rw, rw);
        let out = yh.abs() - rw;
        if out > 0.0 {
            let keep = 1.0 - a.junction;
            let side = &s.sides[if yh >= 0.0 { 0 } else { 1 }];
            let mut extra = s.kerb_m * smooth01(out / 0.06);
            if side.ditch_depth_m > 0.0 {
                let u = (out - side.ditch_start_m) / side.ditch_width_m;
                if u > 0.0 && u < 1.0 {
                    let w = (std::f32::consts::PI * u).sin();
                    extra -= side.ditch_depth_m * w * w;
                }
            }
            extra += side.slope_rise_m * smooth01((out - side.slope_start_m) / side.slope_width_m);
            z += extra * keep;
        }
        z
    }

    /// Upward unit normal at (x, y) (forward differences over 5 cm).
    pub fn normal(&self, x: f32, y: f32) -> V3 {
        let e = 0.05;
        let h = self.height(x, y);
        let hx = (self.height(x + e, y) - h) / e;
        let hy = (self.height(x, y + e) - h) / e;
        V3::new(-hx, -hy, 1.0).normalize()
    }

    /// The first t in (0, t_max) where the ray meets the ground. Secant steps (exact for a
    /// plane), capped so a step never jumps more than 1 m + half the distance travelled; once
    /// the ray is below the ground, the first sign change on a 25 cm grid inside the last step
    /// is refined by regula falsi. Features narrower than 25 cm may be stepped over at grazing
    /// angles (both sensors then miss them alike).
    pub fn intersect(&self, o: &V3, d: &V3, t_max: f32) -> Option<f32> {
        let dn = d.norm();
        let mut t_end = t_max;
        if d.z < 0.0 {
            t_end = t_end.min((o.z - self.z_min) / -d.z);
        } else if o.z > self.max_towards(o.x, d.x) {
            return None;
        }
        let f = |t: f32| {
            let p = o + d * t;
            p.z - self.height(p.x, p.y)
        };
        let (mut t0, mut f0) = (0.0f32, f(0.0));
        if f0 <= 0.0 {
            return None;
        }
        let mut rate = -d.z;
        let rw = self.shape.road_half_width_m;
        for _ in 0..64 {
            // Within the carriageway the ground is smooth (grade and bank only), so a secant
            // step may run up to where the ray leaves it; elsewhere steps are capped.
            let p = o + d * t0;
            let along = self.along(p.x);
            let yh = p.y - along.centre;
            let dyh = d.y - along.centre_slope * d.x;
            // Until it leaves: |ŷ| grows at most by |dŷ/dt|·t + κ·(d.x·t)²/2 (κ bounds |c''|).
            let band = if yh.abs() < rw {
                let margin = if dyh > 0.0 { rw - yh } else { yh + rw };
                let k = self.curvature * d.x * d.x;
                if k > 1e-9 { (-dyh.abs() + (dyh * dyh + 2.0 * k * margin).sqrt()) / k } else { margin / dyh.abs().max(1e-9) }
            } else {
                0.0
            };
            let cap = ((1.0 + 0.5 * t0 * dn) / dn).max(band);
            let step = if rate > 1e-6 { (f0 / rate).min(cap) } else { cap };
            let t1 = (t0 + step.max(1e-4 / dn)).min(t_end);
            let f1 = f(t1);
            if f1 <= 0.0 {
                // A long bracket may hold several crossings (a kerb then a ditch): take the
                // first sign change on a 25 cm grid before refining.
                let n = (((t1 - t0) * dn / 0.25).ceil() as usize).clamp(1, 24);
                let (mut a, mut fa) = (t0, f0);
                for k in 1..n {
                    let t = t0 + (t1 - t0) * k as f32 / n as f32;
                    let ft = f(t);
                    if ft <= 0.0 {
                        return Some(refine(&f, a, fa, t, ft));
                    }
                    (a, fa) = (t, ft);
                }
                return Some(refine(&f, a, fa, t1, f1));
            }
            if t1 >= t_end {
                return None;
            }
            if f1 < 2e-4 {
                return Some(t1);
            }
            rate = (f0 - f1) / (t1 - t0);
            if d.z >= 0.0 && o.z + d.z * t1 > self.max_towards(o.x + d.x * t1, d.x) {
                return None;
            }
            (t0, f0) = (t1, f1);
        }
        None
    }
}

/// Regula falsi (Illinois variant) on a bracket with f(a) > 0 ≥ f(b).
fn refine(f: &impl Fn(f32) -> f32, mut a: f32, mut fa: f32, mut b: f32, mut fb: f32) -> f32 {
    let mut side = 0;
    for _ in 0..24 {
        let t = (a * fb - b * fa) / (fb - fa);
        let ft = f(t);
        if ft.abs() < 1e-4 || (b - a) < 1e-4 {
            return t;
        }
        if ft > 0.0 {
            (a, fa) = (t, ft);
            if side == 1 {
                fb *= 0.5;
            }
            side = 1;
        } else {
            (b, fb) = (t, ft);
            if side == -1 {
                fa *= 0.5;
            }
            side = -1;
        }
    }
    (a + b) * 0.5
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A hilly road with either kerbs (and a sidewalk then a falling slope, like a suburb) or
    /// ditches and embankments (like the countryside); no world puts a ditch right behind a kerb.
    fn hilly(kerb: bool) -> Terrain {
        let shape = RoadShape {
            curve: [[8.0, 300.0, 0.3], [2.0, 90.0, 1.0]],
            profile: [[4.0, 250.0, 0.0], [0.5, 70.0, 2.0]],
            bank_mean: 0.02,
            bank_wave: [0.03, 150.0, 0.5],
            road_half_width_m: 5.0,
            kerb_m: if kerb { 0.15 } else { 0.0 },
            sides: if kerb {
                [
                    Roadside { slope_start_m: 4.0, slope_width_m: 6.0, slope_rise_m: 2.0, ..Roadside::default() },
                    Roadside { slope_start_m: 4.0, slope_width_m: 6.0, slope_rise_m: -1.5, ..Roadside::default() },
                ]
            } else {
                [
                    Roadside { ditch_start_m: 1.0, ditch_width_m: 2.0, ditch_depth_m: 0.6, slope_start_m: 4.0, slope_width_m: 6.0, slope_rise_m: 3.0 },
                    Roadside { slope_start_m: 2.0, slope_width_m: 5.0, slope_rise_m: -2.5, ..Roadside::default() },
                ]
            },
            junctions: vec![(40.0, 5.0)],
        };
        Terrain::new(shape, -200.0, 200.0)
    }

    /// The march finds the same surface a fine brute-force scan finds.
    #[test]
    fn march_matches_brute_force() {
        for kerb in [false, true] {
            march_matches_brute_force_on(&hilly(kerb));
        }
    }

    fn march_matches_brute_force_on(terrain: &Terrain) {
        let mut checked = 0;
        for i in 0..400 {
            let a = i as f32 * 0.37;
            let o = V3::new(-20.0 + i as f32 * 0.2, terrain.along(-20.0 + i as f32 * 0.2).centre - 2.0, 0.0);
            let o = V3::new(o.x, o.y, terrain.height(o.x, o.y) + 1.7);
            let d = V3::new(a.cos(), a.sin(), -0.02 - 0.3 * ((i % 7) as f32 / 7.0));
            let mut brute = None;
            let mut t = 0.0f32;
            while t < 150.0 {
                let p = o + d * t;
                if p.z < terrain.height(p.x, p.y) {
                    brute = Some(t);
                    break;
                }
                t += 0.002;
            }
            let fast = terrain.intersect(&o, &d, 150.0);
            match (brute, fast) {
                (Some(b), Some(f)) => {
                    assert!((b - f).abs() < 0.01 + 0.0005 * b, "ray {i}: brute {b} vs march {f}");
                    checked += 1;
                }
                (None, None) => {}
                other => panic!("ray {i}: {other:?}"),
            }
        }
        assert!(checked > 300, "{checked}");
    }

    #[test]
    fn flat_shape_is_the_ground_plane() {
        let t = Terrain::new(RoadShape::flat(5.0), 0.0, 100.0);
        assert_eq!(t.height(30.0, 17.0), 0.0);
        let hit = t.intersect(&V3::new(10.0, 0.0, 2.0), &V3::new(1.0, 0.0, -0.1), 100.0).unwrap();
        assert!((hit - 20.0).abs() < 1e-3);
        assert!((t.normal(5.0, 5.0) - V3::z()).norm() < 1e-6);
    }
}
