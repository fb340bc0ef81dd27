//! Integration tests: each drives the real `hifar` binary in its own temporary directory.
mod act;
mod bench;
mod common;
mod curriculum;
mod eval;
mod export;
mod facade;
mod report;
mod rollout;
mod runs;
mod train;
mod usage;
