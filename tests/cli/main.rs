//! The `crossview` binary as a user runs it, one module per subcommand or guarantee: demo,
//! eval, model, serve, train, the offline worker pool, and the end-to-end check that what a
//! client of the server receives scores like `crossview eval`.

mod closed_pipe;
mod demo;
mod eval;
mod fail_closed;
mod fit_check;
mod kafka;
mod model;
mod offline_workers;
mod operator_loop;
mod python_package;
mod record_crash;
mod serve;
mod served_identities_wildtrack;
mod sighup_early;
mod subscriber_memory;
mod sync_check;
mod train;
mod train_interrupt;
mod train_population;
