//! `dray`: a distributed renderer for scenes larger than one machine's memory.
//!
//! This binary hosts every actor: the embedded mode (`dray render`), the coordinator,
//! the worker, a stand-alone cache host (`dray cache`), a local cluster of processes,
//! the job client (`dray submit`), the partitioner and the ray-throughput benchmark
//! (`dray bench-rays`).

mod animation_flags;
mod bench_rays;
mod bytes;
mod cache_cmd;
mod cache_host;
mod cluster_cmd;
mod coordinator_cmd;
mod embedded;
mod frames;
mod health_cmd;
mod help_heading;
mod job_flags;
mod kv_flag;
mod light_flags;
mod net_flags;
mod noise_flags;
mod options;
mod partition_cmd;
mod phm_flag;
mod preview;
mod ray_cache_flag;
mod render_cmd;
mod submit_cmd;
mod summary;
mod sweep;
mod sweep_cmd;
mod telemetry;
mod threads;
mod trace_out;
mod view_flags;
mod warm;
mod worker_cmd;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "dray",
    version,
    about = "dray: a distributed ray tracer for scenes larger than one machine"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a scene in this process (embedded mode).
    Render(render_cmd::RenderArgs),
    /// Build the BVH of a mesh and measure closest-hit ray throughput.
    BenchRays(bench_rays::BenchArgs),
    /// Cut a scene into domains and write a scene package (manifest + one file per domain).
    Partition(partition_cmd::PartitionArgs),
    /// Serve the dray.v1 render API (with reflection and health); jobs run on the
    /// registered workers, or in this process while none is registered.
    Coordinator(coordinator_cmd::CoordinatorArgs),
    /// Submit a job to a coordinator, follow its progress and write the image.
    Submit(submit_cmd::SubmitArgs),
    /// Run a coordinator and N workers as local processes on consecutive ports, until
    /// Ctrl-C.
    Cluster(cluster_cmd::ClusterArgs),
    /// Join a coordinator as a worker: own domains, trace rays, stream them to peers
    /// (and host ray caches, unless --no-cache-host).
    Worker(worker_cmd::WorkerArgs),
    /// Serve ray caches for a coordinator's jobs: a stand-alone cache host, until Ctrl-C
    /// or SIGTERM.
    Cache(cache_cmd::CacheArgs),
    /// Render the exact image, then every combination of --vary values, and write what
    /// each costs in error for what it saves in time (results.csv, table.md, pareto.png).
    Sweep(sweep_cmd::SweepArgs),
    /// Ask a dray server for its status (grpc.health.v1): exit 0 when SERVING, 1 with the
    /// reason otherwise (for Docker's HEALTHCHECK and scripts).
    Health(health_cmd::HealthArgs),
}

fn main() -> std::process::ExitCode {
    let cli = match Cli::try_parse() {
        Ok(c) => c,
        Err(e) => {
            use clap::error::ErrorKind;
            if matches!(e.kind(), ErrorKind::DisplayHelp | ErrorKind::DisplayVersion)
                || matches!(
                    e.kind(),
                    ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand
                )
            {
                let _ = e.print();
                return if e.use_stderr() {
                    std::process::ExitCode::from(2)
                } else {
                    std::process::ExitCode::SUCCESS
                };
            }
            // One line, like every other error: clap's first line without its prefix
            // (and, for missing arguments, the indented lines naming them, which clap
            // puts under it).
            let text = e.to_string();
            let mut lines = text.lines();
            let mut first = lines.next().unwrap_or("invalid arguments").to_string();
            if e.kind() == ErrorKind::MissingRequiredArgument {
                for l in lines.take_while(|l| l.starts_with("  ")) {
                    first.push(' ');
                    first.push_str(l.trim());
                }
            }
            eprintln!(
                "dray: error: {} (see dray --help)",
                first.trim_start_matches("error: ")
            );
            return std::process::ExitCode::from(2);
        }
    };
    // The logger, and the OpenTelemetry exporters of the commands that take
    // --otlp-endpoint (`cluster` hands it to its members and exports nothing itself).
    let otlp = match &cli.command {
        Command::Coordinator(a) => Some((&a.otlp, "coordinator")),
        Command::Worker(a) => Some((&a.otlp, "worker")),
        Command::Render(a) => Some((&a.otlp, "render")),
        _ => None,
    };
    let telemetry = match otlp {
        Some((o, role)) => match telemetry::init(o, role) {
            Ok(t) => t,
            Err(e) => {
                telemetry::init_logs();
                let msg: Vec<String> = e.chain().map(|c| c.to_string()).collect();
                eprintln!("dray: error: {}", msg.join(": "));
                return std::process::ExitCode::FAILURE;
            }
        },
        None => {
            telemetry::init_logs();
            None
        }
    };
    let result = match cli.command {
        Command::Render(a) => render_cmd::run(a),
        Command::BenchRays(a) => bench_rays::run(a),
        Command::Partition(a) => partition_cmd::run(a),
        Command::Coordinator(a) => coordinator_cmd::run(a),
        Command::Worker(a) => worker_cmd::run(a),
        Command::Submit(a) => submit_cmd::run(a),
        Command::Cluster(a) => cluster_cmd::run(a),
        Command::Cache(a) => cache_cmd::run(a),
        Command::Sweep(a) => sweep_cmd::run(a),
        Command::Health(a) => health_cmd::run(a),
    };
    // Flush what the exporters still hold (the commands return on Ctrl-C and SIGTERM too).
    if let Some(t) = telemetry {
        t.shutdown();
    }
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            // One line: the error and its causes.
            let msg: Vec<String> = e.chain().map(|c| c.to_string()).collect();
            eprintln!("dray: error: {}", msg.join(": "));
            std::process::ExitCode::FAILURE
        }
    }
}
