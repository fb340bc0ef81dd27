//! `hifar runs` on a real run directory.

use crate::common::{hifar, read_json, stderr, tempdir};
use crate::train::{reference_run, stage_names};

#[test]
fn runs_lists_and_shows_the_reference_run() {
    let run = &reference_run().run;
    let root = run.parent().unwrap();
    let dir = tempdir();
    let out = hifar(dir.path()).args(["runs", "--root"]).arg(root).output().unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let text = String::from_utf8_lossy(&out.stdout);
    let row = text.lines().find(|l| l.starts_with("reference")).unwrap_or_else(|| panic!("{text}"));
    assert!(row.contains("completed"), "{row}");

    let out = hifar(dir.path()).args(["runs", "show"]).arg(run).output().unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let text = String::from_utf8_lossy(&out.stdout);
    let manifest = read_json(&run.join("manifest.json"));
    for name in stage_names(&manifest) {
        assert!(text.lines().any(|l| l.starts_with(&name) && (l.contains("completed") || l.contains("threshold_missed"))), "{text}");
    }
}
