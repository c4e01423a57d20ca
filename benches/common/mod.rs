//! What the criterion benches share.

/// The benches' `main`: criterion's (`criterion_main!`), run on rayon's pool as the
/// `texavatars` binary runs its commands (`texavatars::cpu::threads::on_pool`), so the
/// timings are the binary's.
pub fn main_on_pool(groups: fn()) {
    texavatars::cpu::threads::on_pool(|| {
        groups();
        criterion::Criterion::default()
            .configure_from_args()
            .final_summary();
    });
}
