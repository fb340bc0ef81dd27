//! `hifar report`: plots and a markdown summary of the reference run (with and without an
//! evaluation), and the refusals that happen before Python starts.

use std::path::{Path, PathBuf};

use serde_json::json;

use crate::common::{hifar, read_json, stderr, stdout, tempdir};
use crate::train::{reference_run, stage_names};

/// Width and height of a PNG file (its IHDR chunk), after checking the signature.
fn png_size(path: &Path) -> (u32, u32) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()));
    assert!(bytes.len() > 24 && bytes.starts_with(b"\x89PNG\r\n\x1a\n"), "{} is not a PNG", path.display());
    assert_eq!(&bytes[12..16], b"IHDR", "{}", path.display());
    let word = |at: usize| u32::from_be_bytes(bytes[at..at + 4].try_into().unwrap());
    (word(16), word(20))
}

/// The image links `![...](target)` of a markdown file, resolved against its directory.
fn image_links(markdown: &Path) -> Vec<PathBuf> {
    let text = std::fs::read_to_string(markdown).unwrap();
    let dir = markdown.parent().unwrap();
    text.split("![")
        .skip(1)
        .filter_map(|rest| {
            let start = rest.find("](")? + 2;
            let end = start + rest[start..].find(')')?;
            Some(dir.join(&rest[start..end]))
        })
        .collect()
}

fn assert_plots(markdown: &Path, count: usize) {
    let links = image_links(markdown);
    assert_eq!(links.len(), count, "{}", std::fs::read_to_string(markdown).unwrap());
    for link in links {
        let (w, h) = png_size(&link);
        assert!(w >= 600 && h >= 400, "{} is {w}×{h}", link.display());
    }
}

/// The 95% Wilson score interval of `successes` out of `trials`.
fn wilson(successes: u32, trials: u32) -> [f64; 2] {
    let (n, z) = (f64::from(trials), 1.959963984540054_f64);
    let p = f64::from(successes) / n;
    let denom = 1.0 + z * z / n;
    let centre = (p + z * z / (2.0 * n)) / denom;
    let half = z * (p * (1.0 - p) / n + z * z / (4.0 * n * n)).sqrt() / denom;
    [(centre - half).max(0.0), (centre + half).min(1.0)]
}

#[test]
fn report_of_the_reference_run_plots_its_curves_and_says_there_is_no_evaluation() {
    let run = &reference_run().run;
    let manifest = read_json(&run.join("manifest.json"));
    let dir = tempdir();
    let out = dir.path().join("report");
    let output = hifar(dir.path()).arg("report").arg(run).arg("--out").arg(&out).output().unwrap();
    assert_eq!(output.status.code(), Some(0), "{}", stderr(&output));
    let markdown = out.join("report.md");
    assert_eq!(stdout(&output).trim(), markdown.to_str().unwrap());
    assert!(stderr(&output).contains("3 plots"), "{}", stderr(&output));
    assert_plots(&markdown, 3);
    let text = std::fs::read_to_string(&markdown).unwrap();
    for (name, stage) in stage_names(&manifest).iter().zip(manifest["stages"].as_array().unwrap()) {
        let steps = stage["env_steps"].as_u64().unwrap();
        let row = format!("| {name} | {} | {steps} |", stage["status"].as_str().unwrap());
        assert!(text.contains(&row), "no row {row:?} in\n{text}");
    }
    assert!(text.contains("No evaluation yet"), "{text}");
    assert!(!run.join("report").exists(), "--out must not write into the run");
}

#[test]
fn report_goes_into_the_run_by_default_and_shows_its_evaluations() {
    let reference = &reference_run().run;
    let dir = tempdir();
    let run = dir.path().join("run");
    std::fs::create_dir(&run).unwrap();
    for file in ["manifest.json", "metrics.jsonl"] {
        std::fs::copy(reference.join(file), run.join(file)).unwrap();
    }
    let cell = |experiment: &str, scenario: &str, setting: &str, successes: u32, paper: f64| {
        let rate = f64::from(successes) / 8.0;
        json!({"experiment": experiment, "scenario": scenario, "setting": setting, "value": null,
               "trials": 8, "successes": successes, "success_rate": rate,
               "ci95": wilson(successes, 8),
               "recovery_time_mean": if successes > 0 { json!(2.5) } else { json!(null) },
               "recovery_time_std": if successes > 0 { json!(0.2) } else { json!(null) },
               "paper_success_rate": paper, "paper_recovery_time": null})
    };
    let eval = json!({
        "format_version": 1, "protocol": "quick", "backend": "native", "seed": 0, "trials": 8,
        "checkpoint": "stages/full/checkpoints/000000000256", "stage": null, "env_steps": 256,
        "versions": {}, "conditions": {},
        "cells": [cell("standard", "prone", "standard", 0, 1.0), cell("standard", "supine", "standard", 2, 1.0),
                  cell("planar_push", "prone", "150N", 0, 1.0), cell("planar_push", "supine", "150N", 1, 1.0)],
    });
    std::fs::create_dir_all(run.join("eval").join("quick-native")).unwrap();
    std::fs::write(run.join("eval").join("quick-native").join("eval.json"), eval.to_string()).unwrap();

    for _ in 0..2 {
        // A second report replaces the first one's files.
        let output = hifar(dir.path()).args(["report", "run"]).output().unwrap();
        assert_eq!(output.status.code(), Some(0), "{}", stderr(&output));
        let markdown = run.join("report").join("report.md");
        assert_eq!(stdout(&output).trim(), markdown.to_str().unwrap());
        assert!(stderr(&output).contains("5 plots"), "{}", stderr(&output));
        assert_plots(&markdown, 5);
        let text = std::fs::read_to_string(&markdown).unwrap();
        assert!(text.contains("### Protocol quick"), "{text}");
        assert!(text.contains("| prone · native | 0% [0–32] · 100% |"), "{text}");
    }
}

#[test]
fn report_refuses_what_is_not_a_run_directory() {
    let dir = tempdir();
    let output = hifar(dir.path()).args(["report", "no-such-run"]).output().unwrap();
    assert_eq!(output.status.code(), Some(2), "{}", stderr(&output));
    assert_eq!(stderr(&output).trim(), "error: run directory no-such-run does not exist");

    std::fs::create_dir(dir.path().join("empty")).unwrap();
    let output = hifar(dir.path()).args(["report", "empty"]).output().unwrap();
    assert_eq!(output.status.code(), Some(2), "{}", stderr(&output));
    assert_eq!(stderr(&output).trim(), "error: empty is not a run directory (no manifest.json)");
    assert!(!dir.path().join("empty").join("report").exists());

    std::fs::write(dir.path().join("empty").join("manifest.json"), "{\"format_version\": 1").unwrap();
    let output = hifar(dir.path()).args(["report", "empty"]).output().unwrap();
    assert_eq!(output.status.code(), Some(2), "{}", stderr(&output));
    let message = stderr(&output);
    assert_eq!(message.trim().lines().count(), 1, "{message}");
    assert!(message.contains("manifest.json"), "{message}");
}
