//! Run outputs (design.md §6): `summary.json`, TUM trajectories of estimate and truth per
//! vehicle, `map.csv`, `metrics.csv`, `links.csv`, and `report.html`.

pub mod files;
pub mod report;
pub mod summary;

use crate::record::RunRecord;
use std::path::{Path, PathBuf};
pub use summary::{Summary, summarize, table};

/// Failure to write an output file.
#[derive(Debug, thiserror::Error)]
#[error("writing {path}: {source}")]
pub struct OutputError {
    /// The file.
    pub path: PathBuf,
    /// The cause.
    #[source]
    pub source: std::io::Error,
}

fn write(dir: &Path, name: &str, contents: &str) -> Result<(), OutputError> {
    let path = dir.join(name);
    std::fs::write(&path, contents).map_err(|source| OutputError { path, source })
}

/// Writes every output of `run` into `dir` (created if needed) and returns the summary.
pub fn write_all(run: &RunRecord, dir: &Path) -> Result<Summary, OutputError> {
    std::fs::create_dir_all(dir).map_err(|source| OutputError {
        path: dir.to_path_buf(),
        source,
    })?;
    let summary = summarize(run);
    let json =
        serde_json::to_string_pretty(&summary).unwrap_or_else(|e| format!("{{\"error\":\"{e}\"}}"));
    write(dir, "summary.json", &json)?;
    for v in &run.vehicles {
        let origin = run.time_origin_ns;
        write(
            dir,
            &format!("{}.est.tum", v.name),
            &files::tum(v, false, origin),
        )?;
        write(
            dir,
            &format!("{}.truth.tum", v.name),
            &files::tum(v, true, origin),
        )?;
    }
    write(dir, "map.csv", &files::map_csv(run))?;
    write(dir, "metrics.csv", &files::metrics_csv(run))?;
    write(dir, "links.csv", &files::links_csv(run))?;
    write(dir, "report.html", &report::render(run, &summary))?;
    Ok(summary)
}
