//! Why a tuning starts: the step that changed the characteristic set, and the reason said in
//! the log and in the decision it leads to.

/// Why the characteristic set changed.
#[derive(Clone, Debug)]
pub struct Trigger {
    /// The step that changed the set (or the newest one when none did).
    pub step: u64,
    /// Why, in words (logged, and the reason of the decision).
    pub reason: String,
}
