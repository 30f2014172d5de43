//! Command-line entry point: one binary, one subcommand per job.

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "cmr-agent", version, about = "Camera-in-LiDAR-map localization (CMR-Agent)")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Generate synthetic KITTI-odometry sequences, the demo map and request, or a contact sheet.
    Synth(cmr_agent::synth::cli::Args),
    /// Serve the localization HTTP API.
    Serve(cmr_agent::api::ServeArgs),
    /// Evaluate on a KITTI-odometry directory with the paper's protocol: agent, baselines, tables, plots.
    Eval(cmr_agent::eval::cli::Args),
    /// Localize one request file against one map file, without HTTP (prints the response JSON).
    Localize(cmr_agent::api::offline::LocalizeArgs),
    /// Follow a KITTI-layout drive in a stored map region, frame after frame; writes the trajectory, ATE/RPE, latency, plot.
    Track(cmr_agent::api::track::TrackArgs),
    /// Map regions: `map build` fuses a KITTI-layout sequence's scans into one map file.
    Map(cmr_agent::maps::build::MapArgs),
    /// Print the OpenAPI document (the committed openapi/openapi.json).
    PrintSchema,
}

fn main() -> anyhow::Result<()> {
    cmr_agent::logging::init();
    let cli = Cli::parse();
    match cli.command {
        Command::Synth(args) => cmr_agent::synth::cli::run(args),
        Command::Serve(args) => cmr_agent::api::run_serve(args),
        Command::Eval(args) => cmr_agent::eval::cli::main(args),
        Command::Localize(args) => cmr_agent::api::offline::run(args),
        Command::Track(args) => cmr_agent::api::track::run(args),
        Command::Map(args) => cmr_agent::maps::build::run(args),
        Command::PrintSchema => {
            print!("{}", cmr_agent::api::openapi::schema_json());
            Ok(())
        }
    }
}
