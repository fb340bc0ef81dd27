//! Command-line definitions (clap derive). Parsing only: every command lives in `commands`.

use std::path::PathBuf;

use clap::builder::PossibleValuesParser;
use clap::{Args, Parser, Subcommand, ValueEnum};

use crate::names::names;

/// Train Booster T1 fall-recovery policies with the HiFAR two-stage curriculum.
#[derive(Debug, Parser)]
#[command(name = "hifar", version, about, long_about = None)]
#[command(propagate_version = true)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Create the Python environment (HIFAR_VENV, default <repo>/.venv) with pinned packages.
    Setup(SetupArgs),
    /// Report Python, JAX devices, MuJoCo/MJX/brax and the backend hifar would use.
    Doctor,
    /// Validate a curriculum (Rust schema and Python names) without training.
    Check(CheckArgs),
    /// Train every stage of a curriculum into a run directory.
    Train(TrainArgs),
    /// Expand a checkpoint into a stage's feature layout (no Python).
    ExpandCheckpoint(ExpandArgs),
    /// Deterministic actions of a checkpoint's deployable actor for observation rows.
    Act(ActArgs),
    /// Measure physics and learner throughput (raw mujoco.batch, native env, MJX env, learner).
    Bench(BenchArgs),
    /// Evaluate a policy with the paper's simulation protocols (success rate, recovery time).
    Eval(EvalArgs),
    /// Record one episode of a policy as an MCAP file for Foxglove (optionally a video).
    Rollout(RolloutArgs),
    /// Plots and a markdown summary of a run (learning curves, evaluations).
    Report(ReportArgs),
    /// Export a checkpoint's deployable actor as ONNX, checked against `hifar act`.
    Export(ExportArgs),
    /// List runs, or show one.
    Runs(RunsArgs),
}

#[derive(Debug, Args)]
pub struct SetupArgs {
    /// Recreate the environment even if it is up to date.
    #[arg(long)]
    pub force: bool,
}

#[derive(Debug, Args)]
pub struct CheckArgs {
    /// Curriculum TOML file.
    pub curriculum: PathBuf,
    /// Check only this stage.
    #[arg(long, value_name = "NAME")]
    pub stage: Option<String>,
}

#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Curriculum TOML file.
    pub curriculum: PathBuf,
    /// Run directory [default: runs/<curriculum name>-<UTC time>].
    #[arg(long, value_name = "DIR")]
    pub run_dir: Option<PathBuf>,
    /// Experiment seed (overrides the curriculum's `seed`).
    #[arg(long, value_name = "N")]
    pub seed: Option<u64>,
    /// Parallel environments per stage (overrides every stage's `ppo.num_envs`).
    #[arg(long, value_name = "N")]
    pub num_envs: Option<u32>,
    /// Physics backend (overrides the curriculum's `backend`).
    #[arg(long, value_parser = physics_backend())]
    pub backend: Option<String>,
    /// Continue the run in --run-dir from its last checkpoint.
    #[arg(long, requires = "run_dir", conflicts_with = "force")]
    pub resume: bool,
    /// Start a new run with the leading stages of RUN: each completed stage whose resolved
    /// settings equal this curriculum's (same seed, backend and --num-envs) is copied, in
    /// order, and training starts at the first that differs. Seed, backend and --num-envs
    /// default to RUN's.
    #[arg(long, value_name = "RUN", conflicts_with = "resume")]
    pub reuse_stages_from: Option<PathBuf>,
    /// Delete an existing run directory and start over.
    #[arg(long)]
    pub force: bool,
}

#[derive(Debug, Args)]
pub struct ExpandArgs {
    /// Checkpoint directory to expand.
    pub checkpoint: PathBuf,
    /// Curriculum that defines the target stage.
    #[arg(long, value_name = "FILE")]
    pub curriculum: PathBuf,
    /// Target stage name.
    #[arg(long, value_name = "NAME")]
    pub stage: String,
    /// Output checkpoint directory (must not exist).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
}

#[derive(Debug, Args)]
pub struct ActArgs {
    /// Checkpoint directory.
    pub checkpoint: PathBuf,
    /// JSON file: {"obs": [[...], ...], "history": [[[...]]] (optional)}.
    #[arg(long, value_name = "FILE")]
    pub input: PathBuf,
}

#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Print one JSON document ({"results": [...]}) instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Batch sizes [default: 64 256 1024; with --quick: 16].
    #[arg(long, num_args = 1.., value_name = "N")]
    pub batches: Vec<u32>,
    /// Short measurements without MJX and the learner (their compiles take minutes on a CPU).
    #[arg(long)]
    pub quick: bool,
    /// Skip the MJX environment above this batch size.
    #[arg(long, value_name = "N")]
    pub mjx_max_batch: Option<u32>,
}

#[derive(Debug, Args)]
#[command(args_conflicts_with_subcommands = true)]
pub struct RunsArgs {
    /// Directory holding run directories.
    #[arg(long, value_name = "DIR", default_value = "runs", global = true)]
    pub root: PathBuf,
    #[command(subcommand)]
    pub command: Option<RunsCommand>,
}

#[derive(Debug, Subcommand)]
pub enum RunsCommand {
    /// Details of one run (a run directory, or a run name under --root).
    Show {
        run: PathBuf,
    },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ProtocolArg {
    /// The paper's protocols, every cell (minutes on a GPU, longer on a CPU).
    Paper,
    /// A reduced protocol for CI and smoke checks.
    Quick,
    /// Stand, the six key states, supine and prone under nominal conditions.
    Keystate,
}

impl ProtocolArg {
    pub fn as_str(self) -> &'static str {
        match self {
            ProtocolArg::Paper => "paper",
            ProtocolArg::Quick => "quick",
            ProtocolArg::Keystate => "keystate",
        }
    }
}

#[derive(Debug, Args)]
pub struct EvalArgs {
    /// A checkpoint directory, or a run directory (the final checkpoint of its last completed stage).
    pub target: PathBuf,
    /// Which protocol set to run.
    #[arg(long, value_enum, default_value = "paper")]
    pub protocol: ProtocolArg,
    /// Trials per protocol cell [default: 100 for paper, 8 for quick and keystate].
    #[arg(long, value_name = "N")]
    pub trials: Option<u32>,
    /// Physics backend [default: the machine's default, see `hifar doctor`].
    #[arg(long, value_parser = physics_backend())]
    pub backend: Option<String>,
    /// The actor that acts: `deployable` (the default: adaptation module + base policy, as on
    /// the robot) or `privileged` (the base policy with the encoder's latent from the
    /// simulator's state: the actor PPO trains and the training monitor measures; not
    /// deployable, it shows what the adaptation module loses and evaluates checkpoints of a
    /// stage's PPO phase).
    #[arg(long, value_parser = actor(), value_name = "ACTOR")]
    pub actor: Option<String>,
    /// Seed of every random draw of the evaluation.
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub seed: u64,
    /// Output directory [default: <run>/eval/<protocol>-<backend> or <checkpoint>/eval/<protocol>-<backend>, with -<actor> after a non-default actor].
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Replace an existing output directory.
    #[arg(long)]
    pub force: bool,
}

#[derive(Debug, Args)]
pub struct RolloutArgs {
    /// A checkpoint directory, or a run directory (the final checkpoint of its last completed stage).
    pub target: PathBuf,
    #[arg(long, default_value = "supine", help = one_of_help("Initial scenario", &names().scenarios))]
    pub scenario: String,
    /// A push of this many newtons 0.8 s into the recovery, for 200 ms, as in the paper.
    #[arg(long, value_name = "N")]
    pub push_force: Option<f64>,
    #[arg(long, value_name = "DIR", help = one_of_help(
        "Push direction in the torso frame [default: forward from prone, backward otherwise]",
        &names().push_directions,
    ))]
    pub push_direction: Option<String>,
    #[arg(long, default_value = "flat", help = one_of_help("Terrain", &names().terrains))]
    pub terrain: String,
    /// Seed of the episode's random draws.
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub seed: u64,
    /// Physics backend [default: the machine's default, see `hifar doctor`].
    #[arg(long, value_parser = physics_backend())]
    pub backend: Option<String>,
    /// Episode length in seconds [default: the stage's episode_s].
    #[arg(long, value_name = "S")]
    pub duration: Option<f64>,
    /// Output MCAP file.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    /// Also render an MP4 video (needs an offscreen GL backend: EGL or OSMesa).
    #[arg(long, value_name = "FILE")]
    pub video: Option<PathBuf>,
    /// Also render a PNG filmstrip of snapshots (needs an offscreen GL backend).
    #[arg(long, value_name = "FILE")]
    pub filmstrip: Option<PathBuf>,
    /// Replace existing output files.
    #[arg(long)]
    pub force: bool,
}

#[derive(Debug, Args)]
pub struct ReportArgs {
    /// Run directory.
    pub run: PathBuf,
    /// Output directory [default: <run>/report].
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
}

#[derive(Debug, Args)]
pub struct ExportArgs {
    /// A checkpoint directory, or a run directory (the final checkpoint of its last completed stage).
    pub target: PathBuf,
    /// Output ONNX file.
    #[arg(long, value_name = "FILE")]
    pub onnx: PathBuf,
    /// Replace an existing output file.
    #[arg(long)]
    pub force: bool,
}

/// `what: a, b or c` — the help of a flag whose values are a vocabulary jax_env exports.
fn one_of_help(what: &str, names: &[&str]) -> String {
    match names.split_last() {
        Some((last, rest)) if !rest.is_empty() => format!("{what}: {} or {last}", rest.join(", ")),
        _ => format!("{what}: {}", names.join("")),
    }
}

/// `--actor`: one of the actors jax_env exports.
fn actor() -> PossibleValuesParser {
    PossibleValuesParser::new(names().actors.iter().copied())
}

/// `--backend`: one of the physics backends jax_env exports.
fn physics_backend() -> PossibleValuesParser {
    PossibleValuesParser::new(names().physics_backends.iter().copied())
}
