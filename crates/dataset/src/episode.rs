use std::collections::HashMap;
use std::path::Path;

use glam::Vec3;
use safetensors::{Dtype, SafeTensors, tensor::TensorView};

use crate::{Error, Manipulation, Result, write_atomic};

/// One recorded episode: tracked particle positions and gripper actions per frame.
///
/// Frames are `1 / fps` seconds apart (see [`crate::DatasetMeta`]); positions are in metres.
/// Arrays are stored flat, frame-major: particle `i` at frame `t` is `positions[t * N + i]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Episode {
    frames: usize,
    particles: usize,
    grippers: usize,
    positions: Vec<Vec3>,
    gripper_positions: Vec<Vec3>,
    held: Option<Vec<i32>>,
    closed: Option<Vec<u8>>,
    colors: Option<Vec<[f32; 3]>>,
    visible: Option<Vec<u8>>,
}

fn invalid(message: impl Into<String>) -> Error {
    // Episodes built in memory have no file yet; readers replace this path with the real one.
    Error::invalid("<episode>", message)
}

impl Episode {
    /// An episode of `frames` × `particles` positions and `frames` × `grippers` gripper positions,
    /// validated (sizes match, everything finite, at least one frame, particle and gripper).
    pub fn new(
        frames: usize,
        particles: usize,
        grippers: usize,
        positions: Vec<Vec3>,
        gripper_positions: Vec<Vec3>,
    ) -> Result<Self> {
        if frames == 0 || particles == 0 || grippers == 0 {
            return Err(invalid(format!(
                "an episode needs at least one frame, particle and gripper (got T={frames}, N={particles}, G={grippers})"
            )));
        }
        check_len("positions", positions.len(), frames * particles)?;
        check_len("grippers", gripper_positions.len(), frames * grippers)?;
        check_finite("positions", &positions, particles)?;
        check_finite("grippers", &gripper_positions, grippers)?;
        Ok(Episode {
            frames,
            particles,
            grippers,
            positions,
            gripper_positions,
            held: None,
            closed: None,
            colors: None,
            visible: None,
        })
    }

    /// Sets which gripper holds each particle (−1 for free).
    pub fn with_held(mut self, held: Vec<i32>) -> Result<Self> {
        check_len("held", held.len(), self.particles)?;
        if let Some((i, g)) = held
            .iter()
            .enumerate()
            .find(|(_, g)| **g < -1 || **g >= self.grippers as i32)
        {
            return Err(invalid(format!(
                "held[{i}] = {g} is not -1 or a gripper index below {}",
                self.grippers
            )));
        }
        self.held = Some(held);
        Ok(self)
    }

    /// Sets the per-frame, per-gripper closed flags (`[T × G]`, 0 or 1).
    pub fn with_closed(mut self, closed: Vec<u8>) -> Result<Self> {
        check_len("closed", closed.len(), self.frames * self.grippers)?;
        check_flags("closed", &closed)?;
        self.closed = Some(closed);
        Ok(self)
    }

    /// Sets per-particle RGB colours in [0, 1].
    pub fn with_colors(mut self, colors: Vec<[f32; 3]>) -> Result<Self> {
        check_len("colors", colors.len(), self.particles)?;
        if let Some(i) = colors
            .iter()
            .position(|c| c.iter().any(|v| !(0.0..=1.0).contains(v)))
        {
            return Err(invalid(format!("colors[{i}] is outside [0, 1]")));
        }
        self.colors = Some(colors);
        Ok(self)
    }

    /// Sets per-frame, per-particle visibility flags (`[T × N]`, 0 = occluded).
    pub fn with_visible(mut self, visible: Vec<u8>) -> Result<Self> {
        check_len("visible", visible.len(), self.frames * self.particles)?;
        check_flags("visible", &visible)?;
        self.visible = Some(visible);
        Ok(self)
    }

    /// Number of frames T.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Number of tracked particles N.
    pub fn particles(&self) -> usize {
        self.particles
    }

    /// Number of grippers G.
    pub fn grippers(&self) -> usize {
        self.grippers
    }

    /// Particle positions at frame `t` (metres). Panics if `t >= frames()`.
    pub fn frame(&self, t: usize) -> &[Vec3] {
        &self.positions[t * self.particles..(t + 1) * self.particles]
    }

    /// Gripper positions at frame `t` (metres). Panics if `t >= frames()`.
    pub fn gripper_frame(&self, t: usize) -> &[Vec3] {
        &self.gripper_positions[t * self.grippers..(t + 1) * self.grippers]
    }

    /// All positions, frame-major `[T × N]`.
    pub fn positions(&self) -> &[Vec3] {
        &self.positions
    }

    /// All gripper positions, frame-major `[T × G]`.
    pub fn gripper_positions(&self) -> &[Vec3] {
        &self.gripper_positions
    }

    /// The stored `held` array, if any.
    pub fn held(&self) -> Option<&[i32]> {
        self.held.as_deref()
    }

    /// Whether gripper `g` is closed at frame `t` (true when no `closed` array is stored).
    pub fn closed(&self, t: usize, g: usize) -> bool {
        self.closed
            .as_ref()
            .is_none_or(|c| c[t * self.grippers + g] != 0)
    }

    /// Whether particle `i` is visible at frame `t` (true when no `visible` array is stored).
    pub fn visible(&self, t: usize, i: usize) -> bool {
        self.visible
            .as_ref()
            .is_none_or(|v| v[t * self.particles + i] != 0)
    }

    /// Per-particle colours, if stored.
    pub fn colors(&self) -> Option<&[[f32; 3]]> {
        self.colors.as_deref()
    }

    /// The stored `held`, or the format's default: under `grasp`, each particle within `radius`
    /// metres of a gripper at frame 0 is held by the nearest such gripper; under `push` and
    /// `attach`, none.
    pub fn held_or_default(&self, manipulation: Manipulation, radius: f32) -> Vec<i32> {
        if let Some(h) = &self.held {
            return h.clone();
        }
        if manipulation != Manipulation::Grasp {
            return vec![-1; self.particles];
        }
        let grippers = self.gripper_frame(0);
        self.frame(0)
            .iter()
            .map(|p| {
                let (g, d) = grippers
                    .iter()
                    .enumerate()
                    .map(|(g, q)| (g, p.distance(*q)))
                    .fold((-1i32, f32::INFINITY), |best, (g, d)| {
                        if d < best.1 { (g as i32, d) } else { best }
                    });
                if d <= radius { g } else { -1 }
            })
            .collect()
    }

    /// Serialises to safetensors bytes.
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        let (t, n, g) = (self.frames, self.particles, self.grippers);
        let pos = f32_bytes(self.positions.iter().flat_map(|p| p.to_array()));
        let grip = f32_bytes(self.gripper_positions.iter().flat_map(|p| p.to_array()));
        let mut owned: Vec<(&str, Dtype, Vec<usize>, Vec<u8>)> = vec![
            ("positions", Dtype::F32, vec![t, n, 3], pos),
            ("grippers", Dtype::F32, vec![t, g, 3], grip),
        ];
        if let Some(h) = &self.held {
            let bytes = h.iter().flat_map(|v| v.to_le_bytes()).collect();
            owned.push(("held", Dtype::I32, vec![n], bytes));
        }
        if let Some(c) = &self.closed {
            owned.push(("closed", Dtype::U8, vec![t, g], c.clone()));
        }
        if let Some(c) = &self.colors {
            owned.push((
                "colors",
                Dtype::F32,
                vec![n, 3],
                f32_bytes(c.iter().flatten().copied()),
            ));
        }
        if let Some(v) = &self.visible {
            owned.push(("visible", Dtype::U8, vec![t, n], v.clone()));
        }
        let views = owned
            .iter()
            .map(|(name, dtype, shape, bytes)| {
                TensorView::new(*dtype, shape.clone(), bytes).map(|v| (*name, v))
            })
            .collect::<std::result::Result<Vec<_>, _>>()
            .map_err(|e| invalid(format!("cannot build tensors: {e}")))?;
        let info = HashMap::from([("format".to_string(), crate::FORMAT_VERSION.to_string())]);
        safetensors::serialize(views, Some(info))
            .map_err(|e| invalid(format!("cannot serialise: {e}")))
    }

    /// Parses safetensors bytes; `path` is only used in error messages.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Self> {
        let named = |e: Error| match e {
            Error::Invalid { message, .. } => Error::invalid(path, message),
            other => other,
        };
        Self::parse(bytes).map_err(named)
    }

    fn parse(bytes: &[u8]) -> Result<Self> {
        let st = SafeTensors::deserialize(bytes)
            .map_err(|e| invalid(format!("not a safetensors file: {e}")))?;
        for name in st.names() {
            if !matches!(
                name,
                "positions" | "grippers" | "held" | "closed" | "colors" | "visible"
            ) {
                return Err(invalid(format!("unknown tensor '{name}'")));
            }
        }
        let positions = st
            .tensor("positions")
            .map_err(|_| invalid("missing tensor 'positions' (F32 [T, N, 3])"))?;
        let [t, n] = expect_shape3(&positions, "positions")?;
        let grippers = st
            .tensor("grippers")
            .map_err(|_| invalid("missing tensor 'grippers' (F32 [T, G, 3])"))?;
        let [tg, g] = expect_shape3(&grippers, "grippers")?;
        if tg != t {
            return Err(invalid(format!(
                "'grippers' has {tg} frames but 'positions' has {t}"
            )));
        }
        let mut ep = Episode::new(t, n, g, vec3s(positions.data()), vec3s(grippers.data()))?;
        if let Ok(h) = st.tensor("held") {
            expect(&h, "held", Dtype::I32, &[n])?;
            let held = h
                .data()
                .chunks_exact(4)
                .map(|b| i32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            ep = ep.with_held(held)?;
        }
        if let Ok(c) = st.tensor("closed") {
            expect(&c, "closed", Dtype::U8, &[t, g])?;
            ep = ep.with_closed(c.data().to_vec())?;
        }
        if let Ok(c) = st.tensor("colors") {
            expect(&c, "colors", Dtype::F32, &[n, 3])?;
            let v = f32s(c.data());
            ep = ep.with_colors(v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())?;
        }
        if let Ok(v) = st.tensor("visible") {
            expect(&v, "visible", Dtype::U8, &[t, n])?;
            ep = ep.with_visible(v.data().to_vec())?;
        }
        Ok(ep)
    }

    /// Reads and validates an episode file.
    pub fn read(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        Self::from_bytes(&bytes, path)
    }

    /// Writes the episode atomically.
    pub fn write(&self, path: &Path) -> Result<()> {
        let bytes = self.to_bytes().map_err(|e| match e {
            Error::Invalid { message, .. } => Error::invalid(path, message),
            other => other,
        })?;
        write_atomic(path, &bytes)
    }
}

fn check_len(name: &str, got: usize, want: usize) -> Result<()> {
    if got != want {
        return Err(invalid(format!(
            "'{name}' has {got} entries, expected {want}"
        )));
    }
    Ok(())
}

fn check_finite(name: &str, values: &[Vec3], per_frame: usize) -> Result<()> {
    match values.iter().position(|p| !p.is_finite()) {
        Some(k) => Err(invalid(format!(
            "'{name}' has a non-finite value at frame {}, index {}",
            k / per_frame,
            k % per_frame
        ))),
        None => Ok(()),
    }
}

fn check_flags(name: &str, flags: &[u8]) -> Result<()> {
    match flags.iter().position(|f| *f > 1) {
        Some(k) => Err(invalid(format!(
            "'{name}'[{k}] = {} is not 0 or 1",
            flags[k]
        ))),
        None => Ok(()),
    }
}

fn expect(view: &TensorView<'_>, name: &str, dtype: Dtype, shape: &[usize]) -> Result<()> {
    if view.dtype() != dtype || view.shape() != shape {
        return Err(invalid(format!(
            "'{name}' must be {dtype:?} {shape:?}, found {:?} {:?}",
            view.dtype(),
            view.shape()
        )));
    }
    Ok(())
}

fn expect_shape3(view: &TensorView<'_>, name: &str) -> Result<[usize; 2]> {
    match (view.dtype(), view.shape()) {
        (Dtype::F32, &[a, b, 3]) => Ok([a, b]),
        (d, s) => Err(invalid(format!(
            "'{name}' must be F32 with shape [T, N, 3], found {d:?} {s:?}"
        ))),
    }
}

fn f32s(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

fn vec3s(bytes: &[u8]) -> Vec<Vec3> {
    f32s(bytes)
        .chunks_exact(3)
        .map(|c| Vec3::new(c[0], c[1], c[2]))
        .collect()
}

fn f32_bytes(values: impl Iterator<Item = f32>) -> Vec<u8> {
    values.flat_map(f32::to_le_bytes).collect()
}
