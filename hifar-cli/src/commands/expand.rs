//! `hifar expand-checkpoint`: pure Rust checkpoint surgery (see `checkpoint::expand`).

use anyhow::Result;

use crate::bad_input;
use crate::cli::ExpandArgs;
use crate::commands::check::stage_index;
use crate::{checkpoint, curriculum};

pub fn run(args: &ExpandArgs) -> Result<()> {
    let curriculum = curriculum::load(&args.curriculum)?;
    let stage = &curriculum.stages()[stage_index(&curriculum, &args.stage, &args.curriculum)?];
    if args.out.exists() {
        return Err(bad_input!("{} already exists; choose another --out", args.out.display()));
    }
    let report = checkpoint::expand_to_stage(&args.checkpoint, stage, &args.out)?;
    println!("{report}");
    Ok(())
}
