//! Episode recordings as MCAP files that Foxglove opens (docs/contracts.md, "facade.rollout").
//!
//! `facade.rollout` returns the episode as per-step NumPy arrays, read in one copy each
//! (`python::Facade::call_with_arrays`); [`Recording::from_result`] checks their shapes and
//! dtypes into a typed recording, and [`write_mcap`] writes it: JSON-encoded messages with
//! `jsonschema` schemas, log and publish times the simulated time in nanoseconds. What the
//! values mean (times, poses, names of geoms' bodies) is Python's to get right.
//!
//! | topic           | schema                   | messages                                      |
//! |-----------------|--------------------------|-----------------------------------------------|
//! | `/tf`           | foxglove.FrameTransforms | one per step: world → every body              |
//! | `/scene`        | foxglove.SceneUpdate     | one at t = 0: an entity per body, frame-locked |
//! | `/joint_states` | hifar.JointStates        | one per step: name, position, velocity, effort |
//! | `/torso_pitch`  | hifar.TorsoPitch         | one per step (rad, positive leaning forward)   |
//! | `/rewards`      | hifar.Rewards            | one per step: total and every weighted term    |
//! | `/standing`     | hifar.Standing           | one per step: standing now, success so far     |
//! | `/push`         | hifar.Push               | one per step: the push on the Trunk (world, N) |
//!
//! The foxglove.* schemas follow Foxglove's published JSON schemas (foxglove-sdk,
//! `schemas/jsonschema`) for the fields written here; quaternions are x, y, z, w there and
//! w, x, y, z in MuJoCo.

use std::collections::BTreeMap;
use std::io::Cursor;
use std::path::{Path, PathBuf};

use serde::Deserialize;
use serde_json::{json, Map, Value};

use crate::atomic;
use crate::python::{Array, Arrays, FloatArray};

/// Channels in the order they are added to the file.
pub const TOPICS: [&str; 7] = ["/tf", "/scene", "/joint_states", "/torso_pitch", "/rewards", "/standing", "/push"];

/// The frame every body's transform is given in.
pub const WORLD_FRAME: &str = "world";

#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    #[error("the rollout result is malformed: {0}")]
    Malformed(String),
    #[error("cannot write {}: {source}", path.display())]
    Io { path: PathBuf, source: std::io::Error },
    #[error("cannot encode the MCAP for {}: {source}", path.display())]
    Mcap { path: PathBuf, source: mcap::McapError },
}

/// A collision primitive of the scene, in its body's frame (MuJoCo conventions: `size` holds
/// half-sizes, the radius first; quaternions are w, x, y, z).
#[derive(Debug, Clone, Deserialize)]
pub struct Geom {
    pub name: String,
    pub body: String,
    #[serde(rename = "type")]
    pub kind: GeomKind,
    pub size: [f64; 3],
    pub pos: [f64; 3],
    pub quat: [f64; 4],
    pub rgba: [f64; 4],
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GeomKind {
    Sphere,
    Capsule,
    Box,
}

/// The JSON part of what `facade.rollout` returns; the per-step arrays come beside it.
#[derive(Debug, Deserialize)]
struct Raw {
    dt: f64,
    body_names: Vec<String>,
    joint_names: Vec<String>,
    reward_term_names: Vec<String>,
    push_direction: String,
    success: bool,
    recovery_time: Option<f64>,
    geoms: Vec<Geom>,
    #[serde(default)]
    video: Option<PathBuf>,
    #[serde(default)]
    filmstrip: Option<PathBuf>,
}

/// One value or a row of `width` values per step, in step order (an array [T, …] as Python
/// computed it: float32 for what the environment computed, float64 for what the host did).
#[derive(Debug, Clone)]
pub struct Steps<T> {
    data: Vec<T>,
    width: usize,
}

impl<T: Copy> Steps<T> {
    pub fn row(&self, t: usize) -> &[T] {
        &self.data[t * self.width..(t + 1) * self.width]
    }

    /// Row `t` of a quantity with `N` values a step (checked when the recording was made).
    pub fn row_of<const N: usize>(&self, t: usize) -> [T; N] {
        self.row(t).try_into().expect("the row width was checked")
    }

    pub fn at(&self, t: usize) -> T {
        self.data[t * self.width]
    }
}

impl Steps<f32> {
    /// Row `t` widened to f64 (exactly: every f32 is an f64), as the JSON messages carry it.
    fn row_f64(&self, t: usize) -> Vec<f64> {
        self.row(t).iter().map(|&v| f64::from(v)).collect()
    }
}

/// The element type of an array field of the rollout result.
trait Element: Copy + Sized {
    const DTYPE: &'static str;
    fn of(array: FloatArray) -> Option<Array<Self>>;
}

impl Element for f32 {
    const DTYPE: &'static str = "float32";
    fn of(array: FloatArray) -> Option<Array<f32>> {
        match array {
            FloatArray::F32(a) => Some(a),
            FloatArray::F64(_) => None,
        }
    }
}

impl Element for f64 {
    const DTYPE: &'static str = "float64";
    fn of(array: FloatArray) -> Option<Array<f64>> {
        match array {
            FloatArray::F64(a) => Some(a),
            FloatArray::F32(_) => None,
        }
    }
}

/// Array `name` of the result, which must be `T`s of shape [steps, *row]: the one check that
/// makes indexing by step and row safe. Values are Python's to get right.
fn take<T: Element>(arrays: &mut Arrays, name: &str, steps: Option<usize>, row: &[usize]) -> Result<(Steps<T>, usize), RecordingError> {
    let array = arrays.remove(name).ok_or_else(|| malformed(format!("{name} is missing or not a float array")))?;
    let (shape, dtype) = (array.shape().to_vec(), array.dtype());
    let fits = shape.len() == 1 + row.len() && shape[1..] == *row && steps.is_none_or(|t| shape[0] == t);
    let expected = || {
        let first = steps.map_or_else(|| "T".to_owned(), |t| t.to_string());
        let dims: Vec<String> = std::iter::once(first).chain(row.iter().map(usize::to_string)).collect();
        format!("[{}] {}", dims.join(", "), T::DTYPE)
    };
    match T::of(array) {
        Some(array) if fits => Ok((Steps { width: row.iter().product(), data: array.data }, shape[0])),
        _ => Err(malformed(format!("{name} is {shape:?} {dtype}, expected {}", expected()))),
    }
}

/// One recorded episode, every per-step array checked to have one entry per step.
#[derive(Debug)]
pub struct Recording {
    pub dt: f64,
    pub time: Steps<f64>,
    pub body_names: Vec<String>,
    /// [T, body, 3] (world, m).
    pub body_pos: Steps<f64>,
    /// [T, body, 4] (w, x, y, z).
    pub body_quat: Steps<f64>,
    pub joint_names: Vec<String>,
    pub joint_pos: Steps<f32>,
    pub joint_vel: Steps<f32>,
    pub joint_torque: Steps<f32>,
    pub torso_pitch: Steps<f64>,
    pub reward: Steps<f32>,
    /// Weighted per-step reward of every term, [T, term], terms in the order Python lists them.
    pub reward_term_names: Vec<String>,
    pub reward_terms: Steps<f32>,
    pub standing: Vec<bool>,
    /// Stable standing reached at or before this step (the success detector, latched).
    pub succeeded: Vec<bool>,
    pub push_force: Steps<f32>,
    /// The torso-frame direction of the push (Python's default where none was asked for).
    pub push_direction: String,
    pub success: bool,
    pub recovery_time: Option<f64>,
    pub geoms: Vec<Geom>,
    pub video: Option<PathBuf>,
    pub filmstrip: Option<PathBuf>,
    steps: usize,
}

fn malformed(message: String) -> RecordingError {
    RecordingError::Malformed(message)
}

impl Recording {
    /// The result of `facade.rollout` (its JSON part and its arrays) as a recording.
    pub fn from_result(value: Value, mut arrays: Arrays) -> Result<Recording, RecordingError> {
        let raw: Raw = serde_json::from_value(value).map_err(|err| malformed(err.to_string()))?;
        let (time, steps) = take::<f64>(&mut arrays, "time", None, &[])?;
        if steps == 0 {
            return Err(malformed("the episode has no steps".into()));
        }
        let a = &mut arrays;
        let t = Some(steps);
        let (bodies, joints, terms) = (raw.body_names.len(), raw.joint_names.len(), raw.reward_term_names.len());
        let flag = |steps: Steps<f32>| steps.data.iter().map(|&v| v > 0.5).collect();
        Ok(Recording {
            dt: raw.dt,
            time,
            body_pos: take(a, "body_pos", t, &[bodies, 3])?.0,
            body_quat: take(a, "body_quat", t, &[bodies, 4])?.0,
            joint_pos: take(a, "joint_pos", t, &[joints])?.0,
            joint_vel: take(a, "joint_vel", t, &[joints])?.0,
            joint_torque: take(a, "joint_torque", t, &[joints])?.0,
            torso_pitch: take(a, "torso_pitch", t, &[])?.0,
            reward: take(a, "reward", t, &[])?.0,
            reward_terms: take(a, "reward_terms", t, &[terms])?.0,
            standing: flag(take(a, "standing", t, &[])?.0),
            succeeded: flag(take(a, "succeeded", t, &[])?.0),
            push_force: take(a, "push_force", t, &[3])?.0,
            body_names: raw.body_names,
            joint_names: raw.joint_names,
            reward_term_names: raw.reward_term_names,
            push_direction: raw.push_direction,
            success: raw.success,
            recovery_time: raw.recovery_time,
            geoms: raw.geoms,
            video: raw.video,
            filmstrip: raw.filmstrip,
            steps,
        })
    }

    pub fn steps(&self) -> usize {
        self.steps
    }

    /// Simulated duration covered by the recording (s).
    pub fn duration_s(&self) -> f64 {
        self.time.at(self.steps - 1)
    }
}

/// Messages written per topic.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Written {
    pub messages: BTreeMap<String, u64>,
    pub bytes: u64,
}

/// Nanoseconds of simulated time.
fn nanos(seconds: f64) -> u64 {
    (seconds * 1e9).round().max(0.0) as u64
}

/// A foxglove `time` ({sec, nsec}).
fn stamp(ns: u64) -> Value {
    json!({"sec": ns / 1_000_000_000, "nsec": ns % 1_000_000_000})
}

fn vector3(v: [f64; 3]) -> Value {
    json!({"x": v[0], "y": v[1], "z": v[2]})
}

/// A foxglove quaternion (x, y, z, w) from MuJoCo's (w, x, y, z).
fn quaternion(q: [f64; 4]) -> Value {
    json!({"x": q[1], "y": q[2], "z": q[3], "w": q[0]})
}

fn pose(pos: [f64; 3], quat: [f64; 4]) -> Value {
    json!({"position": vector3(pos), "orientation": quaternion(quat)})
}

fn color(rgba: [f64; 4]) -> Value {
    json!({"r": rgba[0], "g": rgba[1], "b": rgba[2], "a": rgba[3]})
}

/// `v` rotated by the unit quaternion `q` (w, x, y, z).
fn rotate(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
    let [w, x, y, z] = q;
    // t = 2 (q_xyz × v); v' = v + w t + q_xyz × t
    let t = [2.0 * (y * v[2] - z * v[1]), 2.0 * (z * v[0] - x * v[2]), 2.0 * (x * v[1] - y * v[0])];
    [v[0] + w * t[0] + (y * t[2] - z * t[1]), v[1] + w * t[1] + (z * t[0] - x * t[2]), v[2] + w * t[2] + (x * t[1] - y * t[0])]
}

/// The Foxglove primitives of one geom: a sphere, a box, or a capsule as a cylinder between two
/// spheres (Foxglove has no capsule; both have their axis along the local z).
fn primitives(geom: &Geom, spheres: &mut Vec<Value>, cubes: &mut Vec<Value>, cylinders: &mut Vec<Value>) {
    let c = color(geom.rgba);
    match geom.kind {
        GeomKind::Sphere => {
            let d = 2.0 * geom.size[0];
            spheres.push(json!({"pose": pose(geom.pos, geom.quat), "size": vector3([d, d, d]), "color": c}));
        }
        GeomKind::Box => {
            let s = geom.size.map(|h| 2.0 * h);
            cubes.push(json!({"pose": pose(geom.pos, geom.quat), "size": vector3(s), "color": c}));
        }
        GeomKind::Capsule => {
            let (r, h) = (geom.size[0], geom.size[1]);
            let d = 2.0 * r;
            cylinders.push(json!({
                "pose": pose(geom.pos, geom.quat), "size": vector3([d, d, 2.0 * h]),
                "bottom_scale": 1.0, "top_scale": 1.0, "color": c.clone(),
            }));
            for sign in [-1.0, 1.0] {
                let offset = rotate(geom.quat, [0.0, 0.0, sign * h]);
                let centre = [geom.pos[0] + offset[0], geom.pos[1] + offset[1], geom.pos[2] + offset[2]];
                spheres.push(json!({"pose": pose(centre, geom.quat), "size": vector3([d, d, d]), "color": c.clone()}));
            }
        }
    }
}

/// The `/scene` message: one frame-locked entity per body (its collision primitives in its
/// frame) and one for the world (the floor, the obstacle).
fn scene_update(rec: &Recording, ns: u64) -> Value {
    let frames = rec.body_names.iter().map(String::as_str).chain([WORLD_FRAME]);
    let entities: Vec<Value> = frames
        .map(|frame| {
            let (mut spheres, mut cubes, mut cylinders) = (Vec::new(), Vec::new(), Vec::new());
            for geom in rec.geoms.iter().filter(|g| g.body == frame) {
                primitives(geom, &mut spheres, &mut cubes, &mut cylinders);
            }
            json!({
                "timestamp": stamp(ns), "frame_id": frame, "id": frame,
                "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": true,
                "metadata": [], "arrows": [], "cubes": cubes, "spheres": spheres,
                "cylinders": cylinders, "lines": [], "triangles": [], "texts": [], "models": [],
            })
        })
        .collect();
    json!({"deletions": [], "entities": entities})
}

// ---------------------------------------------------------------------------------------------
// Schemas (jsonschema).

fn s_time() -> Value {
    json!({"type": "object", "title": "time", "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}})
}

fn s_duration() -> Value {
    json!({"type": "object", "title": "duration", "properties": {
        "sec": {"type": "integer"}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}})
}

fn s_object(title: &str, properties: &[(&str, Value)]) -> Value {
    let props: Map<String, Value> = properties.iter().map(|(k, v)| (k.to_string(), v.clone())).collect();
    let required: Vec<&str> = properties.iter().map(|(k, _)| *k).collect();
    json!({"title": title, "type": "object", "properties": props, "required": required})
}

fn s_number() -> Value {
    json!({"type": "number"})
}

fn s_vector3() -> Value {
    s_object("foxglove.Vector3", &[("x", s_number()), ("y", s_number()), ("z", s_number())])
}

fn s_quaternion() -> Value {
    s_object("foxglove.Quaternion", &[("x", s_number()), ("y", s_number()), ("z", s_number()), ("w", s_number())])
}

fn s_pose() -> Value {
    s_object("foxglove.Pose", &[("position", s_vector3()), ("orientation", s_quaternion())])
}

fn s_color() -> Value {
    s_object("foxglove.Color", &[("r", s_number()), ("g", s_number()), ("b", s_number()), ("a", s_number())])
}

fn s_array(items: Value) -> Value {
    json!({"type": "array", "items": items})
}

fn frame_transforms_schema() -> Value {
    let transform = s_object(
        "foxglove.FrameTransform",
        &[
            ("timestamp", s_time()),
            ("parent_frame_id", json!({"type": "string"})),
            ("child_frame_id", json!({"type": "string"})),
            ("translation", s_vector3()),
            ("rotation", s_quaternion()),
        ],
    );
    s_object("foxglove.FrameTransforms", &[("transforms", s_array(transform))])
}

fn scene_update_schema() -> Value {
    let sized = |title: &str| s_object(title, &[("pose", s_pose()), ("size", s_vector3()), ("color", s_color())]);
    let cylinder = s_object(
        "foxglove.CylinderPrimitive",
        &[("pose", s_pose()), ("size", s_vector3()), ("bottom_scale", s_number()), ("top_scale", s_number()), ("color", s_color())],
    );
    let key_value = s_object("foxglove.KeyValuePair", &[("key", json!({"type": "string"})), ("value", json!({"type": "string"}))]);
    // Primitive kinds this file never writes: always empty arrays.
    let unused = || s_array(json!({"type": "object"}));
    let entity = s_object(
        "foxglove.SceneEntity",
        &[
            ("timestamp", s_time()),
            ("frame_id", json!({"type": "string"})),
            ("id", json!({"type": "string"})),
            ("lifetime", s_duration()),
            ("frame_locked", json!({"type": "boolean"})),
            ("metadata", s_array(key_value)),
            ("arrows", unused()),
            ("cubes", s_array(sized("foxglove.CubePrimitive"))),
            ("spheres", s_array(sized("foxglove.SpherePrimitive"))),
            ("cylinders", s_array(cylinder)),
            ("lines", unused()),
            ("triangles", unused()),
            ("texts", unused()),
            ("models", unused()),
        ],
    );
    let deletion = s_object(
        "foxglove.SceneEntityDeletion",
        &[("timestamp", s_time()), ("type", json!({"type": "integer", "enum": [0, 1]})), ("id", json!({"type": "string"}))],
    );
    s_object("foxglove.SceneUpdate", &[("deletions", s_array(deletion)), ("entities", s_array(entity))])
}

fn s_numbers() -> Value {
    s_array(s_number())
}

fn joint_states_schema() -> Value {
    s_object(
        "hifar.JointStates",
        &[
            ("timestamp", s_time()),
            ("name", s_array(json!({"type": "string"}))),
            ("position", s_numbers()),
            ("velocity", s_numbers()),
            ("effort", s_numbers()),
        ],
    )
}

fn rewards_schema(terms: &[String]) -> Value {
    let props: Vec<(&str, Value)> = terms.iter().map(|t| (t.as_str(), s_number())).collect();
    s_object("hifar.Rewards", &[("timestamp", s_time()), ("total", s_number()), ("terms", s_object("hifar.RewardTerms", &props))])
}

/// (topic, schema name, schema) of every channel.
fn channels(rec: &Recording) -> Vec<(&'static str, &'static str, Value)> {
    vec![
        ("/tf", "foxglove.FrameTransforms", frame_transforms_schema()),
        ("/scene", "foxglove.SceneUpdate", scene_update_schema()),
        ("/joint_states", "hifar.JointStates", joint_states_schema()),
        ("/torso_pitch", "hifar.TorsoPitch", s_object("hifar.TorsoPitch", &[("timestamp", s_time()), ("pitch", s_number())])),
        ("/rewards", "hifar.Rewards", rewards_schema(&rec.reward_term_names)),
        (
            "/standing",
            "hifar.Standing",
            s_object(
                "hifar.Standing",
                &[("timestamp", s_time()), ("standing", json!({"type": "boolean"})), ("success", json!({"type": "boolean"}))],
            ),
        ),
        (
            "/push",
            "hifar.Push",
            s_object(
                "hifar.Push",
                &[("timestamp", s_time()), ("frame_id", json!({"type": "string"})), ("force", s_vector3()), ("magnitude", s_number())],
            ),
        ),
    ]
}

/// The messages of step `t`, by topic (without `/scene`).
fn step_messages(rec: &Recording, t: usize, ns: u64) -> [(&'static str, Value); 6] {
    let (pos, quat) = (rec.body_pos.row(t), rec.body_quat.row(t));
    let transforms: Vec<Value> = rec
        .body_names
        .iter()
        .enumerate()
        .map(|(b, name)| {
            json!({
                "timestamp": stamp(ns), "parent_frame_id": WORLD_FRAME, "child_frame_id": name,
                "translation": vector3(pos[3 * b..3 * b + 3].try_into().expect("3 values a body")),
                "rotation": quaternion(quat[4 * b..4 * b + 4].try_into().expect("4 values a body")),
            })
        })
        .collect();
    let terms: Map<String, Value> =
        rec.reward_term_names.iter().zip(rec.reward_terms.row(t)).map(|(term, &v)| (term.clone(), json!(f64::from(v)))).collect();
    let f = rec.push_force.row_of::<3>(t).map(f64::from);
    [
        ("/tf", json!({"transforms": transforms})),
        (
            "/joint_states",
            json!({
                "timestamp": stamp(ns), "name": rec.joint_names, "position": rec.joint_pos.row_f64(t),
                "velocity": rec.joint_vel.row_f64(t), "effort": rec.joint_torque.row_f64(t),
            }),
        ),
        ("/torso_pitch", json!({"timestamp": stamp(ns), "pitch": rec.torso_pitch.at(t)})),
        ("/rewards", json!({"timestamp": stamp(ns), "total": f64::from(rec.reward.at(t)), "terms": terms})),
        ("/standing", json!({"timestamp": stamp(ns), "standing": rec.standing[t], "success": rec.succeeded[t]})),
        (
            "/push",
            json!({
                "timestamp": stamp(ns), "frame_id": WORLD_FRAME, "force": vector3(f),
                "magnitude": (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt(),
            }),
        ),
    ]
}

/// The MCAP file's bytes: schemas, channels, the `/scene` at t = 0, then every step's
/// messages in time order, and a `hifar.rollout` metadata record (`metadata`).
pub fn encode(rec: &Recording, metadata: &BTreeMap<String, String>) -> Result<(Vec<u8>, BTreeMap<String, u64>), mcap::McapError> {
    let options = mcap::WriteOptions::new().library(format!("hifar {}", env!("CARGO_PKG_VERSION")));
    let mut writer = options.create(Cursor::new(Vec::new()))?;
    let mut ids: BTreeMap<&str, u16> = BTreeMap::new();
    for (topic, name, schema) in channels(rec) {
        let schema_id = writer.add_schema(name, "jsonschema", &serde_json::to_vec(&schema).expect("schemas serialize"))?;
        let channel_id = writer.add_channel(schema_id, topic, "json", &BTreeMap::new())?;
        ids.insert(topic, channel_id);
    }
    let mut counts: BTreeMap<String, u64> = TOPICS.iter().map(|t| (t.to_string(), 0)).collect();
    let mut write = |writer: &mut mcap::Writer<_>, topic: &str, ns: u64, message: &Value| -> Result<(), mcap::McapError> {
        let count = counts.get_mut(topic).expect("known topic");
        let header = mcap::records::MessageHeader { channel_id: ids[topic], sequence: *count as u32, log_time: ns, publish_time: ns };
        *count += 1;
        writer.write_to_known_channel(&header, &serde_json::to_vec(message).expect("messages serialize"))
    };
    let start = nanos(rec.time.at(0));
    write(&mut writer, "/scene", start, &scene_update(rec, start))?;
    for t in 0..rec.steps() {
        let ns = nanos(rec.time.at(t));
        for (topic, message) in step_messages(rec, t, ns) {
            write(&mut writer, topic, ns, &message)?;
        }
    }
    writer.write_metadata(&mcap::records::Metadata { name: "hifar.rollout".into(), metadata: metadata.clone() })?;
    writer.finish()?;
    let bytes = writer.into_inner().into_inner();
    Ok((bytes, counts))
}

/// Writes the recording to `path` atomically (a temporary sibling, fsynced, renamed).
pub fn write_mcap(path: &Path, rec: &Recording, metadata: &BTreeMap<String, String>) -> Result<Written, RecordingError> {
    let (bytes, messages) = encode(rec, metadata).map_err(|source| RecordingError::Mcap { path: path.to_path_buf(), source })?;
    atomic::write_file_atomic(path, &bytes).map_err(|source| RecordingError::Io { path: path.to_path_buf(), source })?;
    Ok(Written { messages, bytes: bytes.len() as u64 })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every step the same: one row `row` repeated `steps` times, as Python would send it.
    fn per<T: Copy>(steps: usize, row: &[T], shape: &[usize]) -> Array<T> {
        let shape = [steps].into_iter().chain(shape.iter().copied()).collect();
        Array { shape, data: (0..steps).flat_map(|_| row.iter().copied()).collect() }
    }

    fn tiny(steps: usize) -> (Value, Arrays) {
        let h = std::f64::consts::FRAC_1_SQRT_2; // a quarter turn about x
        let value = json!({
            "dt": 0.02, "body_names": ["Trunk", "Waist"], "joint_names": ["Waist"],
            "reward_term_names": ["survival", "standing"],
            "push_direction": "backward", "success": false, "recovery_time": null,
            "geoms": [
                {"name": "trunk", "body": "Trunk", "type": "box", "size": [0.1, 0.1, 0.2], "pos": [0.0, 0.0, 0.0], "quat": [1.0, 0.0, 0.0, 0.0], "rgba": [0.5, 0.5, 0.5, 1.0]},
                {"name": "leg", "body": "Waist", "type": "capsule", "size": [0.05, 0.1, 0.0], "pos": [0.0, 0.0, 0.0], "quat": [h, h, 0.0, 0.0], "rgba": [0.5, 0.5, 0.5, 1.0]},
                {"name": "floor", "body": "world", "type": "box", "size": [10.0, 10.0, 0.01], "pos": [0.0, 0.0, -0.01], "quat": [1.0, 0.0, 0.0, 0.0], "rgba": [0.5, 0.5, 0.5, 1.0]}
            ],
            "video": null, "filmstrip": null
        });
        let time = Array { shape: vec![steps], data: (0..steps).map(|i| i as f64 * 0.02).collect() };
        let arrays: Arrays = [
            ("time", FloatArray::F64(time)),
            ("body_pos", FloatArray::F64(per(steps, &[0.0, 0.0, 0.6, 0.0, 0.0, 0.5], &[2, 3]))),
            ("body_quat", FloatArray::F64(per(steps, &[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0], &[2, 4]))),
            ("joint_pos", FloatArray::F32(per(steps, &[0.1], &[1]))),
            ("joint_vel", FloatArray::F32(per(steps, &[0.0], &[1]))),
            ("joint_torque", FloatArray::F32(per(steps, &[1.5], &[1]))),
            ("torso_pitch", FloatArray::F64(per(steps, &[0.2], &[]))),
            ("reward", FloatArray::F32(per(steps, &[1.0], &[]))),
            ("reward_terms", FloatArray::F32(per(steps, &[0.5, 0.5], &[2]))),
            ("standing", FloatArray::F32(per(steps, &[1.0], &[]))),
            ("succeeded", FloatArray::F32(per(steps, &[0.0], &[]))),
            ("push_force", FloatArray::F32(per(steps, &[0.0, 0.0, 0.0], &[3]))),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_owned(), v))
        .collect();
        (value, arrays)
    }

    fn recording(steps: usize) -> Recording {
        let (value, arrays) = tiny(steps);
        Recording::from_result(value, arrays).unwrap()
    }

    #[test]
    fn every_step_gets_one_message_per_topic_and_the_scene_one() {
        let rec = recording(5);
        let (bytes, counts) = encode(&rec, &BTreeMap::new()).unwrap();
        assert_eq!(counts["/scene"], 1);
        for topic in TOPICS.iter().filter(|t| **t != "/scene") {
            assert_eq!(counts[*topic], 5, "{topic}");
        }
        let summary = mcap::Summary::read(&bytes).unwrap().expect("summary written");
        let stats = summary.stats.expect("statistics");
        assert_eq!(stats.message_count, 31);
        assert_eq!((stats.message_start_time, stats.message_end_time), (0, 80_000_000));
        let schemas: Vec<String> = summary.schemas.values().map(|s| s.name.clone()).collect();
        assert!(schemas.contains(&"foxglove.FrameTransforms".to_string()) && schemas.contains(&"foxglove.SceneUpdate".to_string()));
    }

    #[test]
    fn capsules_become_a_cylinder_and_two_spheres_along_the_geom_axis() {
        let rec = recording(1);
        let scene = scene_update(&rec, 0);
        let entities = scene["entities"].as_array().unwrap();
        assert_eq!(entities.len(), 3, "Trunk, Waist and the world");
        let waist = &entities[1];
        assert_eq!(waist["frame_id"], "Waist");
        assert_eq!(waist["frame_locked"], true);
        assert_eq!(waist["cylinders"].as_array().unwrap().len(), 1);
        let spheres = waist["spheres"].as_array().unwrap();
        assert_eq!(spheres.len(), 2);
        // Rotated 90° about x, the capsule's local z axis points along world −y.
        let y: Vec<f64> = spheres.iter().map(|s| s["pose"]["position"]["y"].as_f64().unwrap()).collect();
        assert!((y[0] - 0.1).abs() < 1e-12 && (y[1] + 0.1).abs() < 1e-12, "{y:?}");
        assert_eq!(entities[0]["cubes"][0]["size"], json!({"x": 0.2, "y": 0.2, "z": 0.4}));
    }

    #[test]
    fn quaternions_are_reordered_and_shapes_checked() {
        assert_eq!(quaternion([1.0, 2.0, 3.0, 4.0]), json!({"x": 2.0, "y": 3.0, "z": 4.0, "w": 1.0}));
        let (value, mut arrays) = tiny(3);
        arrays.insert("reward".into(), FloatArray::F32(per(2, &[1.0], &[])));
        let err = Recording::from_result(value, arrays).unwrap_err().to_string();
        assert!(err.contains("reward is [2] float32, expected [3] float32"), "{err}");
        let (value, mut arrays) = tiny(3);
        arrays.insert("body_pos".into(), FloatArray::F32(per(3, &[0.0; 6], &[2, 3])));
        let err = Recording::from_result(value, arrays).unwrap_err().to_string();
        assert!(err.contains("body_pos is [3, 2, 3] float32, expected [3, 2, 3] float64"), "{err}");
        let (value, mut arrays) = tiny(3);
        arrays.remove("time");
        let err = Recording::from_result(value, arrays).unwrap_err().to_string();
        assert!(err.contains("time is missing or not a float array"), "{err}");
    }

    #[test]
    fn float32_values_reach_the_messages_exactly() {
        let rec = recording(1);
        let messages = step_messages(&rec, 0, 0);
        // 0.1f32 widened to f64 (0.10000000149011612), as Python's float() of it reads.
        assert_eq!(messages[1].1["position"], json!([f64::from(0.1f32)]));
        assert_eq!(messages[2].1["pitch"], json!(0.2));
    }
}
