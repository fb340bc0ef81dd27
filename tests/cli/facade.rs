//! The facade requests: the CLI's serde structs and jax_env's dataclasses
//! (`jax_env/facade_requests.py`) have the same fields in the same order.

use std::process::Command;

use hifar_cli::commands::facade::request_fields;
use serde_json::{json, Value};

use crate::common::{repo_root, require_venv, stderr, stdout};

#[test]
fn facade_requests_match_the_python_dataclasses() {
    let python = require_venv().join("bin").join("python");
    let script = "import json\nfrom jax_env import facade_requests as r\n\
                  print(json.dumps({name: r.fields(cls) for name, cls in r.REQUESTS.items()}))";
    let out = Command::new(python).current_dir(repo_root()).args(["-c", script]).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    let python: Value = serde_json::from_str(&stdout(&out)).unwrap();
    let rust: serde_json::Map<String, Value> = request_fields().into_iter().map(|(name, fields)| (name.to_owned(), json!(fields))).collect();
    assert_eq!(Value::Object(rust), python);
}
