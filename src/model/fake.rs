//! A deterministic stand-in for the four graphs, for fast tests of what surrounds inference
//! (scheduler, search, admission, failure isolation). Outputs follow the contract's shapes and
//! norms; their values are simple functions of the inputs, not a trained model.
//!
//! One hook makes a single request misbehave on purpose: an image tensor whose first value is
//! above [`FakeBackend::POISON`] yields image features that carry it into the agent's `state_2d`,
//! and the agent answers NaN logits for exactly that row.

use std::sync::Arc;

use anyhow::{Result, bail};

use super::{AgentOutput, Backend, Manifest, Points, point_tensor};

pub struct FakeBackend {
    manifest: Arc<Manifest>,
    /// Policy calls made, and rows stepped (for batching tests).
    pub calls: usize,
    pub rows: usize,
    policy: Option<PolicyHook>,
}

/// A test's own policy, or a watch on the calls: called with each policy call's `(state_2d,
/// state_3d, batch)` after the inputs' shapes are checked; `Some` answers in place of the fake
/// policy, `None` lets it answer.
pub type PolicyHook = Box<dyn FnMut(&[f32], &[f32], usize) -> Option<AgentOutput> + Send>;

impl FakeBackend {
    /// Image tensors whose first value exceeds this poison their agent rows (see module docs).
    pub const POISON: f32 = 100.0;

    pub fn new(manifest: Arc<Manifest>) -> Self {
        Self { manifest, calls: 0, rows: 0, policy: None }
    }

    /// The fake encoders with `hook` before (or in place of) the fake policy.
    pub fn with_policy(manifest: Arc<Manifest>, hook: PolicyHook) -> Self {
        Self { policy: Some(hook), ..Self::new(manifest) }
    }
}

fn normalise(v: &mut [f32]) {
    let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
    v.iter_mut().for_each(|x| *x /= norm);
}

impl Backend for FakeBackend {
    fn manifest(&self) -> &Arc<Manifest> {
        &self.manifest
    }

    /// A function of each point alone; for a set that reads intensity, of its rank too (the
    /// 4th column of [`point_tensor`]).
    fn encode_points(&mut self, points: Points<'_>) -> Result<Vec<f32>> {
        let d = self.manifest.features.dim;
        let c = self.manifest.point_channels();
        let input = point_tensor(&self.manifest, points)?;
        let mut out = Vec::with_capacity(points.len() * d);
        for p in input.chunks_exact(c) {
            if !p.iter().all(|v| v.is_finite()) {
                bail!("output \"point_features\" contains non-finite values");
            }
            let start = out.len();
            let angle = |k: usize| p[0] * 0.37 * (k + 1) as f32 + p[1] * 0.11 * k as f32 + p[2] * 0.05;
            if c == 4 {
                out.extend((0..d).map(|k| (angle(k) + p[3] * 0.7 * (k % 5) as f32).sin() + 0.01));
            } else {
                out.extend((0..d).map(|k| angle(k).sin() + 0.01));
            }
            normalise(&mut out[start..]);
        }
        Ok(out)
    }

    fn encode_image(&mut self, image: &[f32]) -> Result<Vec<f32>> {
        let n = self.manifest.image_feature_len();
        let plane = n / self.manifest.features.dim;
        let mean = image.iter().sum::<f32>() / image.len().max(1) as f32;
        let mut out: Vec<f32> = (0..n).map(|i| ((i / plane) as f32 * 0.3 + mean).cos()).collect();
        for cell in 0..plane {
            let mut v: Vec<f32> = (0..self.manifest.features.dim).map(|k| out[k * plane + cell]).collect();
            normalise(&mut v);
            for (k, x) in v.into_iter().enumerate() {
                out[k * plane + cell] = x;
            }
        }
        if image.first().is_some_and(|&v| v > Self::POISON) {
            out[0] = image[0];
        }
        Ok(out)
    }

    fn frustum_logits(&mut self, point_features: &[f32], image_features: &[f32]) -> Result<Vec<f32>> {
        let d = self.manifest.features.dim;
        let plane = image_features.len() / d;
        Ok(point_features.chunks(d).map(|f| f.iter().enumerate().map(|(k, x)| x * image_features[k * plane]).sum::<f32>() * 4.0).collect())
    }

    fn agent_step(&mut self, state_2d: &[f32], state_3d: &[f32], batch: usize) -> Result<AgentOutput> {
        let (l2, l3) = (self.manifest.state_2d_len(), self.manifest.points.num_state_points * 5);
        if state_2d.len() != batch * l2 || state_3d.len() != batch * l3 {
            bail!("agent inputs do not hold {batch} states");
        }
        self.calls += 1;
        self.rows += batch;
        if let Some(answer) = self.policy.as_mut().and_then(|hook| hook(state_2d, state_3d, batch)) {
            return Ok(answer);
        }
        let a = self.manifest.num_actions();
        let mut policy_logits = vec![0f32; batch * 3 * a];
        let mut value = vec![0f32; batch];
        for b in 0..batch {
            let row = &mut policy_logits[b * 3 * a..(b + 1) * 3 * a];
            if state_2d[b * l2] > Self::POISON {
                row.fill(f32::NAN);
                value[b] = f32::NAN;
                continue;
            }
            // A step of at most one notch per DoF, chosen by the observation: deterministic, and
            // the zero step comes up often enough that trajectories stop.
            let s: f32 = state_3d[b * l3..b * l3 + 64].iter().sum();
            for dof in 0..3 {
                let pick = a / 2 - 1 + ((s.abs() * 1000.0) as usize + dof) % 3;
                row[dof * a + pick] = 5.0;
            }
            value[b] = s.tanh();
        }
        Ok(AgentOutput { policy_logits, value })
    }
}
