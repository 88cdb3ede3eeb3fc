//! The loop every trainer shares: optimizer steps until the end of the schedule, a stop
//! request (Ctrl-C), `--stop-at` or the session's time budget; a progress bar; evaluations
//! every `eval_every` steps and at the end; checkpoints every `checkpoint_every` steps and on
//! the way out. What a step and an evaluation are is the trainer's ([`Steps`]).

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use candle_core::Var;
use candle_core::backprop::GradStore;
use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};

use super::TrainError;
use super::checkpoint::TrainState;
use super::optim::{Optimizer, clip_grad_norm, learning_rate};

/// A run's length, learning-rate schedule (warm-up, then cosine), gradient clipping, and when
/// it evaluates and checkpoints. Both trainers flatten it into their `train.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    /// The schedule's length (the progress bar's total).
    pub steps: u64,
    pub warmup_steps: u64,
    pub lr: f64,
    /// The cosine ends at `lr` x this.
    pub min_lr_ratio: f64,
    pub grad_clip: f64,
    pub checkpoint_every: u64,
    pub eval_every: u64,
}

/// A trainer, as the loop sees it.
pub trait Steps {
    /// What is prepared once per session (a data prefetcher, a clock, the variables).
    type Session;
    type Report;

    /// Steps taken so far, and the training time they took.
    fn state(&self) -> &TrainState;
    fn plan(&self) -> &Plan;
    fn begin(&mut self) -> Result<Self::Session, TrainError>;
    /// One optimizer step (logged); returns the progress bar's message.
    fn train_step(&mut self, session: &mut Self::Session) -> Result<String, TrainError>;
    /// Evaluates and logs (and keeps the best weights); `None` when there is nothing to
    /// evaluate on.
    fn evaluate(&mut self) -> Result<Option<Self::Report>, TrainError>;
    fn report_line(step: u64, report: &Self::Report) -> String;
    fn save_checkpoint(&self) -> Result<(), TrainError>;
}

/// A session's trainable variables, and its clock (added to the time of earlier sessions).
pub struct SessionClock {
    pub vars: Vec<Var>,
    started: Instant,
    base_elapsed: f64,
}

impl SessionClock {
    pub fn new(vars: Vec<Var>, state: &TrainState) -> Self {
        Self { vars, started: Instant::now(), base_elapsed: state.elapsed_s }
    }
}

/// The end of every optimizer step: refuse a non-finite loss, clip, take the scheduled
/// learning rate, update, and count the step and the time. Returns (lr, gradient norm).
pub fn update(
    loss: f64,
    mut grads: GradStore,
    optimizer: &mut Optimizer,
    state: &mut TrainState,
    plan: &Plan,
    clock: &SessionClock,
) -> Result<(f64, f64), TrainError> {
    if !loss.is_finite() {
        return Err(TrainError::Config(format!(
            "the loss became {loss} at step {}: lower the learning rate",
            state.step
        )));
    }
    let grad_norm = clip_grad_norm(&mut grads, &clock.vars, plan.grad_clip)?;
    let lr = learning_rate(state.step, plan.warmup_steps, plan.steps, plan.lr, plan.min_lr_ratio);
    optimizer.step(&grads, lr)?;
    state.step += 1;
    state.elapsed_s = clock.base_elapsed + clock.started.elapsed().as_secs_f64();
    Ok((lr, grad_norm))
}

/// Where a session ends short of the schedule.
#[derive(Debug, Clone, Copy, Default)]
pub struct SessionLimits {
    /// Stop at this step (checkpointed, to be resumed; the schedule still spans its length).
    pub stop_at: Option<u64>,
    /// Wall-clock time for the whole session, its final evaluation and checkpoint included:
    /// steps stop early enough for the evaluation to fit, judged by how long the last one
    /// took (before any, a sixth of the budget is kept for it).
    pub time_budget: Option<Duration>,
}

impl SessionLimits {
    /// Whether another step still leaves time for the final evaluation.
    fn time_left(&self, started: Instant, last_eval: Option<Duration>) -> bool {
        self.time_budget.is_none_or(|budget| {
            let reserve = last_eval.unwrap_or(budget / 6);
            started.elapsed() + reserve < budget
        })
    }
}

/// How a session ended (each evaluation was printed as it came).
#[derive(Debug, Clone)]
pub struct RunSummary {
    pub state: TrainState,
    /// Stopped by a stop request rather than the schedule or `stop_at`.
    pub interrupted: bool,
    /// Stopped because the time budget was spent.
    pub out_of_time: bool,
}

/// Trains until the configured step count, a stop request or one of `limits` (checkpointed,
/// to be resumed; the schedule still spans the configured count). A session that runs out of
/// time evaluates its last step before it ends.
///
/// With `evaluate_first`, a run that has taken no step yet evaluates its weights before the
/// first one (within the time budget). Why: a run that starts from trained weights keeps as
/// best only what an evaluation saw, and fine-tunings that lowered the loss have decoded worse
/// than the weights they started from (`docs/decisions.md`, "Training on a GPU"); evaluated
/// first, those weights stay the best until a step beats them.
pub fn run<T: Steps>(
    trainer: &mut T,
    stop: &AtomicBool,
    limits: SessionLimits,
    evaluate_first: bool,
    progress: bool,
) -> Result<RunSummary, TrainError> {
    let started = Instant::now();
    let (steps, eval_every, checkpoint_every) = {
        let plan = trainer.plan();
        (plan.steps, plan.eval_every.max(1), plan.checkpoint_every.max(1))
    };
    let end = limits.stop_at.map_or(steps, |s| s.min(steps));
    let bar = progress_bar(trainer.state().step, steps, progress);
    let mut session = trainer.begin()?;
    let (mut interrupted, mut out_of_time, mut last_eval) = (false, false, None);
    // Evaluates and prints the report (above the bar, or alone without one); keeps the step
    // it evaluated; returns how long it took.
    let evaluate = |trainer: &mut T, last_eval: &mut Option<u64>| {
        let t0 = Instant::now();
        if let Some(report) = bar.suspend(|| trainer.evaluate())? {
            let step = trainer.state().step;
            let line = T::report_line(step, &report);
            if bar.is_hidden() {
                eprintln!("{line}")
            } else {
                bar.println(line)
            }
            *last_eval = Some(step);
        }
        Ok::<_, TrainError>(t0.elapsed())
    };
    // How long the last evaluation took: what the final one is expected to take.
    let mut reserve = None;
    if evaluate_first && trainer.state().step == 0 {
        reserve = Some(evaluate(trainer, &mut last_eval)?);
    }
    while trainer.state().step < end {
        if stop.load(Ordering::SeqCst) {
            interrupted = true;
            break;
        }
        if !limits.time_left(started, reserve) {
            out_of_time = true;
            if last_eval != Some(trainer.state().step) {
                evaluate(trainer, &mut last_eval)?;
            }
            break;
        }
        let message = trainer.train_step(&mut session)?;
        let step = trainer.state().step;
        bar.set_position(step);
        bar.set_message(message);
        if step.is_multiple_of(eval_every) || step == end {
            reserve = Some(evaluate(trainer, &mut last_eval)?);
        }
        if step.is_multiple_of(checkpoint_every) {
            trainer.save_checkpoint()?;
        }
    }
    trainer.save_checkpoint()?;
    bar.finish_and_clear();
    Ok(RunSummary { state: trainer.state().clone(), interrupted, out_of_time })
}

fn progress_bar(start: u64, total: u64, visible: bool) -> ProgressBar {
    if !visible {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(total);
    if let Ok(style) = ProgressStyle::with_template(
        "{elapsed_precise} [{bar:30}] step {pos}/{len} {msg} ETA {eta}",
    ) {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_position(start);
    bar
}
