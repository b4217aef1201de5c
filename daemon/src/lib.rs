//! Periscope's daemon: capture plans, the pipeline that runs them, run storage, the
//! HTTP API and the `periscope` command line.
//!
//! The `periscope` binary is a thin shell over this library: it parses arguments with
//! [`cli::Cli`], sets up logging with [`logging`], and hands over to [`cli::execute`].
//! Everything it does can therefore be driven from tests without a process.
#![warn(missing_docs)]

pub mod access;
pub mod adaptive;
pub mod admin;
pub mod api;
pub mod budget;
pub mod calibrate;
pub mod capture;
pub mod catalogue;
pub mod check;
pub mod cli;
pub mod config;
pub mod devices;
pub mod events;
#[cfg(feature = "test-hooks")]
pub mod fuzz;
pub mod logging;
pub mod metrics;
pub mod offline;
pub mod pipeline;
pub mod plan;
pub mod priority;
pub mod progress;
pub mod record;
pub mod run_dir;
pub mod service;
pub mod signals;
pub mod store;
pub mod ytal;
