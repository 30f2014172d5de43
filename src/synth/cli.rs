//! `cmr-agent synth ...`: generate sequences (the default), `synth demo`, `synth contact-sheet`,
//! `synth bench`, `synth stats`. This module depends on the subcommands, never the reverse.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};

use super::args::WorldArgs;
use super::generate::generate;
use super::{bench, contact_sheet, demo, rigs, stats};

#[derive(Debug, clap::Args)]
#[command(args_conflicts_with_subcommands = true)]
pub struct Args {
    #[command(subcommand)]
    pub action: Option<Action>,
    #[command(flatten)]
    pub generate: GenerateArgs,
}

#[derive(Debug, clap::Subcommand)]
pub enum Action {
    /// Write the shipped demo map (maps/demo.*) and localize request (examples/localize-demo*).
    Demo(demo::DemoArgs),
    /// Render a grid of frames with the LiDAR projected onto them (a visual sensor check).
    ContactSheet(contact_sheet::ContactSheetArgs),
    /// Time the camera render, LiDAR sweep and PNG encoding per frame (writes nothing).
    Bench(bench::BenchArgs),
    /// Share of LiDAR points on ground, buildings, vegetation, vehicles, ... per world family.
    Stats(stats::StatsArgs),
}

#[derive(Debug, clap::Args)]
pub struct GenerateArgs {
    /// Output root; sequences are written to OUT/00, OUT/01, ...
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[arg(long, default_value_t = 1)]
    pub sequences: usize,
    #[arg(long, default_value_t = 20)]
    pub frames: usize,
    /// Number of the first sequence (so sets can be extended without clashing).
    #[arg(long, default_value_t = 0)]
    pub first_sequence: usize,
    /// Replace existing sequence directories.
    #[arg(long)]
    pub overwrite: bool,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    /// Print the rigs `--rig` accepts, with their parameters, and exit.
    #[arg(long)]
    pub list_rigs: bool,
    #[command(flatten)]
    pub world: WorldArgs,
}

pub fn run(args: Args) -> Result<()> {
    match args.action {
        Some(Action::Demo(a)) => demo::run(&a),
        Some(Action::ContactSheet(a)) => contact_sheet::run(&a),
        Some(Action::Bench(a)) => bench::run(&a),
        Some(Action::Stats(a)) => stats::run(&a),
        None => {
            let g = args.generate;
            if g.list_rigs {
                print!("{}", rigs::list());
                return Ok(());
            }
            let Some(out) = g.out else { bail!("--out DIR is required (where the sequences are written)") };
            let config = g.world.config(g.sequences, g.first_sequence, g.frames);
            config.validate()?;
            std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
            let summary = generate(&config, &out, g.overwrite, !g.quiet)?;
            tracing::info!(
                frames = summary.frames,
                seconds = format!("{:.1}", summary.seconds),
                frames_per_s = format!("{:.2}", summary.frames as f64 / summary.seconds),
                mean_points = summary.points / summary.frames.max(1),
                "wrote {} sequence(s) to {}",
                config.sequences,
                out.display()
            );
            Ok(())
        }
    }
}
