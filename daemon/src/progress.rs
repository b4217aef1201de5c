//! The CLI's view of a run: progress bars on a terminal, a line per milestone in the
//! log otherwise. Fed by the same typed events the run writes to `events.jsonl`.
use indicatif::{ProgressBar, ProgressStyle};
use periscope_recon::gtr::TrainEvent;

use crate::events::{EventSink, RunEvent, Stage};

/// Attaches a progress display to `events`.
pub fn attach(events: &EventSink) {
    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template("{prefix:>14} [{bar:30}] {pos}/{len} {msg} ({elapsed})")
            .expect("valid template")
            .progress_chars("=> "),
    );
    let mut last_logged = 0usize;
    events.listen(move |e| match e {
        RunEvent::StageStarted { stage } => {
            bar.set_prefix(stage.name());
            bar.set_position(0);
            bar.set_length(0);
            bar.set_message("");
            tracing::info!(stage = stage.name(), "stage started");
        }
        RunEvent::StageFinished { stage, seconds } => {
            tracing::info!(
                stage = stage.name(),
                seconds = format!("{seconds:.1}"),
                "stage finished"
            );
            if *stage == Stage::Outputs {
                bar.finish_and_clear();
            }
        }
        RunEvent::LosPoint { done, total } => {
            bar.set_length(*total as u64);
            bar.set_position(*done as u64);
        }
        RunEvent::Relay { returns, kept } => tracing::info!(returns, kept, "relay extracted"),
        RunEvent::Planned {
            pairs,
            unreachable,
            requested,
        } => tracing::info!(pairs, unreachable, requested, "pairs planned"),
        RunEvent::Pair { done, total, .. } => {
            bar.set_length(*total as u64);
            bar.set_position(*done as u64);
            if *done >= last_logged + (*total / 4).max(1) || done == total {
                last_logged = *done;
                if bar.is_hidden() {
                    tracing::info!(done, total, "pairs captured");
                }
            }
        }
        RunEvent::Train(TrainEvent::Epoch { epoch, loss, .. }) => {
            bar.set_message(format!("fit epoch {epoch}, loss {loss:.4e}"));
            if bar.is_hidden() && *epoch > 0 {
                tracing::info!(epoch, loss, "fit epoch");
            }
        }
        RunEvent::Train(TrainEvent::Converged { epoch, of, step }) => {
            tracing::info!(
                epoch,
                of,
                step,
                "fit converged: the last stage's loss stopped falling ([gtr] tolerance)"
            );
        }
        RunEvent::PairsChosen(c) => {
            tracing::info!(
                batch = c.batch,
                how = %c.how,
                pairs = c.pairs.len(),
                by_distance = c.explored,
                relative_gain = c.relative_gain.map(|g| format!("{g:.3}")),
                travel_m = format!("{:.2}", c.travel_m),
                measured = c.measured,
                "pairs chosen"
            );
        }
        RunEvent::Suspended { reason, resume } => {
            bar.set_message(format!("suspended: {reason}"));
            tracing::warn!(resume = %resume, "suspended, laser off: {reason}");
        }
        RunEvent::SuspendCleared { reason } => {
            bar.set_message("");
            tracing::info!("suspension cleared ({reason}); measuring again");
        }
        RunEvent::Train(_)
        | RunEvent::Histogram { .. }
        | RunEvent::Safety { .. }
        | RunEvent::Output { .. }
        | RunEvent::Completed => {}
        RunEvent::Failed { message } => {
            bar.abandon_with_message("failed");
            tracing::error!("{message}");
        }
    });
}
