//! Training metrics: one JSON object per iteration in `metrics.jsonl`, and TensorBoard scalars.
//!
//! The TensorBoard event file is written directly: a TFRecord stream (little-endian u64 length,
//! masked CRC-32C of the length, the record, masked CRC-32C of the record) of `Event` protocol
//! buffers, the first carrying `file_version = "brain.Event:2"`, the rest a `Summary` of
//! `simple_value` scalars. Only the handful of protobuf fields TensorBoard reads are encoded.

use std::fs::{self, File, OpenOptions};
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};

use serde_json::{Map, Value};

/// Appends `metrics.jsonl` lines (flushed after every line: a crash loses at most one).
pub struct MetricsLog {
    file: File,
}

impl MetricsLog {
    pub fn open(path: &Path) -> io::Result<MetricsLog> {
        Ok(MetricsLog { file: OpenOptions::new().create(true).append(true).open(path)? })
    }

    pub fn append(&mut self, record: &Value) -> io::Result<()> {
        let mut line = serde_json::to_vec(record)?;
        line.push(b'\n');
        self.file.write_all(&line)
    }
}

/// Reads every parseable line of a `metrics.jsonl` (a torn last line is skipped).
pub fn read_jsonl(path: &Path) -> io::Result<Vec<Value>> {
    let text = match fs::read_to_string(path) {
        Ok(text) => text,
        Err(err) if err.kind() == io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(err) => return Err(err),
    };
    Ok(text.lines().filter_map(|line| serde_json::from_str(line).ok()).collect())
}

/// The scalars of one progress report, with TensorBoard tags: top-level numbers under their
/// own name, nested dicts (`losses`, `rewards`, `monitor`, …) as `<dict>/<key>`, at any depth
/// (`monitor/stand_rate/<scenario>`). Nulls, strings and lists are skipped.
pub fn scalars(progress: &Map<String, Value>) -> Vec<(String, f64)> {
    const SKIP: &[&str] = &["iteration", "env_steps", "total_env_steps", "wall_time", "elapsed_s"];
    let mut out = Vec::new();
    for (key, value) in progress {
        if !SKIP.contains(&key.as_str()) {
            flatten(key.clone(), value, &mut out);
        }
    }
    out
}

fn flatten(tag: String, value: &Value, out: &mut Vec<(String, f64)>) {
    match value {
        Value::Number(n) => out.extend(n.as_f64().map(|f| (tag, f))),
        Value::Object(inner) => {
            for (name, value) in inner {
                flatten(format!("{tag}/{name}"), value, out);
            }
        }
        _ => {}
    }
}

/// `monitor.mean_stand_rate` of a progress report or metrics line: the deterministic
/// monitor's mean stand rate over its scenarios, on the iterations where it ran.
pub fn monitor_mean_stand_rate(progress: &Value) -> Option<f64> {
    progress.get("monitor")?.get("mean_stand_rate")?.as_f64()
}

/// A TensorBoard event file (`events.out.tfevents.<secs>.<host>`).
pub struct EventWriter {
    out: BufWriter<File>,
    path: PathBuf,
}

impl EventWriter {
    /// Creates a new event file in `dir` (created if needed).
    pub fn create(dir: &Path, wall_time: f64, host: &str) -> io::Result<EventWriter> {
        fs::create_dir_all(dir)?;
        let mut name = format!("events.out.tfevents.{}.{}", wall_time as u64, host);
        let mut n = 1;
        while dir.join(&name).exists() {
            name = format!("events.out.tfevents.{}.{}.{n}", wall_time as u64, host);
            n += 1;
        }
        let path = dir.join(name);
        let file = OpenOptions::new().create_new(true).write(true).open(&path)?;
        let mut writer = EventWriter { out: BufWriter::new(file), path };
        let mut event = Vec::new();
        put_double(&mut event, 1, wall_time);
        put_varint_field(&mut event, 2, 0);
        put_bytes(&mut event, 3, b"brain.Event:2");
        writer.write_record(&event)?;
        writer.flush()?;
        Ok(writer)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Writes one event holding `values` as scalars at `step`.
    pub fn scalars(&mut self, step: i64, wall_time: f64, values: &[(String, f64)]) -> io::Result<()> {
        if values.is_empty() {
            return Ok(());
        }
        let mut summary = Vec::new();
        for (tag, value) in values {
            let mut entry = Vec::new();
            put_bytes(&mut entry, 1, tag.as_bytes());
            put_key(&mut entry, 2, WIRE_FIXED32);
            entry.extend_from_slice(&(*value as f32).to_le_bytes());
            put_bytes(&mut summary, 1, &entry);
        }
        let mut event = Vec::new();
        put_double(&mut event, 1, wall_time);
        put_varint_field(&mut event, 2, step as u64);
        put_bytes(&mut event, 5, &summary);
        self.write_record(&event)
    }

    pub fn flush(&mut self) -> io::Result<()> {
        self.out.flush()
    }

    fn write_record(&mut self, data: &[u8]) -> io::Result<()> {
        let len = (data.len() as u64).to_le_bytes();
        self.out.write_all(&len)?;
        self.out.write_all(&masked_crc(&len).to_le_bytes())?;
        self.out.write_all(data)?;
        self.out.write_all(&masked_crc(data).to_le_bytes())
    }
}

impl Drop for EventWriter {
    fn drop(&mut self) {
        let _ = self.out.flush();
    }
}

/// TFRecord's masked CRC-32C.
pub fn masked_crc(data: &[u8]) -> u32 {
    let crc = crc32c::crc32c(data);
    crc.rotate_right(15).wrapping_add(0xa282_ead8)
}

const WIRE_VARINT: u8 = 0;
const WIRE_FIXED64: u8 = 1;
const WIRE_BYTES: u8 = 2;
const WIRE_FIXED32: u8 = 5;

fn put_varint(buf: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        buf.push((v as u8) | 0x80);
        v >>= 7;
    }
    buf.push(v as u8);
}

fn put_key(buf: &mut Vec<u8>, field: u32, wire: u8) {
    put_varint(buf, (u64::from(field) << 3) | u64::from(wire));
}

fn put_varint_field(buf: &mut Vec<u8>, field: u32, v: u64) {
    put_key(buf, field, WIRE_VARINT);
    put_varint(buf, v);
}

fn put_double(buf: &mut Vec<u8>, field: u32, v: f64) {
    put_key(buf, field, WIRE_FIXED64);
    buf.extend_from_slice(&v.to_le_bytes());
}

fn put_bytes(buf: &mut Vec<u8>, field: u32, bytes: &[u8]) {
    put_key(buf, field, WIRE_BYTES);
    put_varint(buf, bytes.len() as u64);
    buf.extend_from_slice(bytes);
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    /// Splits a TFRecord stream, checking both CRCs of every record.
    fn records(bytes: &[u8]) -> Vec<&[u8]> {
        let mut out = Vec::new();
        let mut at = 0;
        while at < bytes.len() {
            let len_bytes = &bytes[at..at + 8];
            let len = u64::from_le_bytes(len_bytes.try_into().unwrap()) as usize;
            let len_crc = u32::from_le_bytes(bytes[at + 8..at + 12].try_into().unwrap());
            assert_eq!(len_crc, masked_crc(len_bytes));
            let data = &bytes[at + 12..at + 12 + len];
            let crc = u32::from_le_bytes(bytes[at + 12 + len..at + 16 + len].try_into().unwrap());
            assert_eq!(crc, masked_crc(data));
            out.push(data);
            at += 16 + len;
        }
        out
    }

    #[test]
    fn masked_crc_matches_tensorflow() {
        // crc32c("") = 0; masked = rotr(0, 15) + 0xa282ead8.
        assert_eq!(masked_crc(b""), 0xa282_ead8);
        // crc32c("123456789") = 0xe3069283 (the CRC-32C check value).
        assert_eq!(crc32c::crc32c(b"123456789"), 0xe306_9283);
        assert_eq!(masked_crc(b"123456789"), 0xe306_9283u32.rotate_right(15).wrapping_add(0xa282_ead8));
    }

    #[test]
    fn event_file_frames_version_then_scalars() {
        let dir = tempfile::tempdir().unwrap();
        let mut writer = EventWriter::create(dir.path(), 1_700_000_000.5, "host").unwrap();
        writer.scalars(42, 1_700_000_001.0, &[("reward/a".into(), 0.5)]).unwrap();
        writer.flush().unwrap();
        let bytes = fs::read(writer.path()).unwrap();
        let recs = records(&bytes);
        assert_eq!(recs.len(), 2);
        // Event{wall_time=1, step=2, file_version=3}.
        let mut first = vec![0x09];
        first.extend_from_slice(&1_700_000_000.5f64.to_le_bytes());
        first.extend_from_slice(&[0x10, 0x00, 0x1a, 13]);
        first.extend_from_slice(b"brain.Event:2");
        assert_eq!(recs[0], &first[..]);
        // Event{wall_time, step=42, summary=5{value=1{tag=1, simple_value=2}}}.
        let mut value = vec![0x0a, 8];
        value.extend_from_slice(b"reward/a");
        value.push(0x15);
        value.extend_from_slice(&0.5f32.to_le_bytes());
        let mut second = vec![0x09];
        second.extend_from_slice(&1_700_000_001.0f64.to_le_bytes());
        second.extend_from_slice(&[0x10, 42, 0x2a, value.len() as u8 + 2, 0x0a, value.len() as u8]);
        second.extend_from_slice(&value);
        assert_eq!(recs[1], &second[..]);
    }

    #[test]
    fn scalars_flatten_nested_metrics() {
        let progress = json!({
            "iteration": 3, "env_steps": 100, "steps_per_s": 12.5, "phase": "ppo",
            "stand_rate": null, "losses": {"policy": 0.1}, "rewards": {"survival": 1.0}
        });
        let tags = scalars(progress.as_object().unwrap());
        assert_eq!(
            tags,
            vec![
                ("steps_per_s".to_string(), 12.5),
                ("losses/policy".to_string(), 0.1),
                ("rewards/survival".to_string(), 1.0)
            ]
        );
    }

    #[test]
    fn scalars_flatten_the_monitor_and_skip_nulls() {
        let progress = json!({
            "env_steps": 100, "max_height": 0.61, "time_standing": null, "penalty_scale": 0.5,
            "monitor": {
                "stand_rate": {"supine": 0.5, "stand": 1.0},
                "recovery_time": {"supine": 2.5, "stand": null},
                "max_height": {"supine": 0.7, "stand": 0.68},
                "mean_stand_rate": 0.75
            }
        });
        let tags = scalars(progress.as_object().unwrap());
        let expected: Vec<(String, f64)> = [
            ("max_height", 0.61),
            ("penalty_scale", 0.5),
            ("monitor/stand_rate/supine", 0.5),
            ("monitor/stand_rate/stand", 1.0),
            ("monitor/recovery_time/supine", 2.5),
            ("monitor/max_height/supine", 0.7),
            ("monitor/max_height/stand", 0.68),
            ("monitor/mean_stand_rate", 0.75),
        ]
        .into_iter()
        .map(|(t, v)| (t.to_string(), v))
        .collect();
        assert_eq!(tags, expected);
    }

    #[test]
    fn jsonl_skips_a_torn_last_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.jsonl");
        let mut log = MetricsLog::open(&path).unwrap();
        log.append(&json!({"iteration": 1})).unwrap();
        drop(log);
        fs::OpenOptions::new().append(true).open(&path).unwrap().write_all(b"{\"iter").unwrap();
        assert_eq!(read_jsonl(&path).unwrap(), vec![json!({"iteration": 1})]);
    }
}
