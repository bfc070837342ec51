//! The precompute's settings as command-line flags: [`PrecomputeOptions`], one clap
//! [`Args`](clap::Args) shared by `translux-precompute` (flattened into its command line),
//! the server's upload jobs and the Table 1 benchmark (`tests/examples/table1.rs`).
//!
//! In: the flags, grouped in `--help` under Patches, Form factors, Subsurface, Output and
//! Resources. Out: [`PrecomputeOptions::params`], the [`PrecomputeParams`] of
//! [`crate::pipeline::precompute`], the one place the flags are checked against each other
//! and `--subsurface auto` is resolved. [`PrecomputeOptions::default`] is what the command
//! line gives with none of these flags.
//!
//! ```
//! use translux_precompute::options::PrecomputeOptions;
//! let params = PrecomputeOptions { patches: Some(2000), ..Default::default() }
//!     .params()
//!     .unwrap();
//! // `--subsurface auto`: a hierarchical S with the default hierarchical F and no T.
//! assert!(params.subsurface_links.is_some());
//! ```

use translux_engine::envvis::{EnvVisParams, parse_bins};
use translux_engine::linkbound::LinkTolerance;

use crate::formfactor::FormFactorParams;
use crate::hierarchy::HierarchyParams;
use crate::pipeline::{FormFactorMethod, PrecomputeParams, hierarchical_s_by_default};
use crate::slinks::{DEFAULT_LINK_NEAR, SLinkParams};

/// `--help` headings.
const PATCHES: &str = "Patches";
const FORM_FACTORS: &str = "Form factors";
const SUBSURFACE: &str = "Subsurface";
const OUTPUT: &str = "Output";
const RESOURCES: &str = "Resources";

/// The precompute's flags (all but the scene, the output folder and the run's mode).
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct PrecomputeOptions {
    /// Target patch count (overrides the scene file; builtin:cornell defaults to 24,640).
    #[arg(long, help_heading = PATCHES)]
    pub patches: Option<u64>,
    /// Maximum patch edge in scene units (instead of a count).
    #[arg(long, conflicts_with = "patches", help_heading = PATCHES)]
    pub max_edge: Option<f32>,
    /// How F is stored: `hierarchical` (a cluster tree and, per patch, links to whole
    /// clusters far enough away: F̃ = C·P) or `dense` (one entry per visible patch pair,
    /// O(N²): for validation and small scenes).
    #[arg(long, value_enum, default_value_t = Transport::Hierarchical, help_heading = FORM_FACTORS)]
    pub transport: Transport,
    /// Hierarchical F only: a cluster of radius R is linked whole only from a distance of
    /// at least R / ACCURACY (it bounds the angle a link subtends). Smaller is more accurate
    /// and larger; accepted 0.02 to 1.
    #[arg(long, default_value_t = HierarchyParams::default().accuracy, help_heading = FORM_FACTORS)]
    pub accuracy: f32,
    /// Hierarchical F only: which side of a link may be a cluster: `one-sided` (each
    /// receiver patch links to source clusters) or `two-sided` (clusters receive too:
    /// links between nodes on both sides, O(N) links at a fixed accuracy; one box only, not
    /// with --shard).
    #[arg(long, value_enum, default_value_t = Links::OneSided, help_heading = FORM_FACTORS)]
    pub links: Links,
    /// Dense F only: drop form factors below this value and report the power they carried.
    #[arg(long, default_value_t = 0.0, help_heading = FORM_FACTORS)]
    pub threshold: f32,
    /// How S is stored inside translucent objects: `pairwise` (one entry per patch pair
    /// within the profile's reach), `hierarchical` (near pairs as pairs, far parts of the
    /// object through whole cluster nodes of F's tree; needs `--transport hierarchical`),
    /// or `auto` (default): hierarchical with the hierarchical transport unless `--inverse`
    /// asks for T (which needs a pairwise S), pairwise otherwise.
    #[arg(long, value_enum, default_value_t = Subsurface::Auto, help_heading = SUBSURFACE)]
    pub subsurface: Subsurface,
    /// Hierarchical S only: a node of radius R is linked whole only from a distance of at
    /// least R / S_ACCURACY; accepted 0.05 to 1.
    #[arg(long, default_value_t = SLinkParams::default().accuracy, help_heading = SUBSURFACE)]
    pub s_accuracy: f32,
    /// Hierarchical S only: link cluster nodes from this many receiver sizes away (1 to 3,
    /// default 1; 1.5 comes a little closer to the pairwise S), each link read at two
    /// distances (the node's straight-line spread about its representative's optical
    /// distance). Nearer links store fewer direct pairs: a translucency change writes fewer
    /// entries and the subsurface stage takes less time.
    #[arg(long, value_name = "K", default_value_t = DEFAULT_LINK_NEAR, help_heading = SUBSURFACE)]
    pub s_link_near: f32,
    /// Hierarchical S only: the largest relative variation of the profile across a linked
    /// node, (R(d − ρ) − R(d + ρ)) / mean, at every translucency from ×1/8 to ×8 of the
    /// scene's (0.01 to 2; smaller is more accurate and stores more). Nodes too small to
    /// matter (10⁻⁶ of the total reflectance) are linked whatever it is.
    #[arg(long, default_value_t = LinkTolerance::DEFAULT_VARIATION, help_heading = SUBSURFACE)]
    pub s_link_variation: f32,
    /// Also compute the transfer matrix T = (I − S F)⁻¹ S.
    #[arg(long, help_heading = OUTPUT)]
    pub inverse: bool,
    /// Environment-light visibility bins, ROWSxCOLS (default 16x32: 2 bytes per patch and
    /// bin), or 0 to skip the stage (environment lights are then refused for the bundle).
    #[arg(long, value_name = "ROWSxCOLS", help_heading = OUTPUT)]
    pub env_bins: Option<String>,
    /// Worker threads (default: all cores).
    #[arg(long, help_heading = RESOURCES)]
    pub threads: Option<usize>,
    /// Refuse when the estimated peak memory exceeds this many GiB (default: 85% of free).
    #[arg(long, help_heading = RESOURCES)]
    pub max_memory_gib: Option<f64>,
}

/// `--transport`: how F is stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Transport {
    Dense,
    Hierarchical,
}

/// `--links`: which sides of a hierarchical F's links may be clusters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Links {
    OneSided,
    TwoSided,
}

/// `--subsurface`: how S is stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Subsurface {
    // Hierarchical where it can be (the hierarchical F and no T), pairwise otherwise (a
    // doc comment here would show in `--help`, in its long form).
    Auto,
    Pairwise,
    Hierarchical,
}

impl Default for PrecomputeOptions {
    /// What the command line gives with none of these flags (their clap defaults).
    fn default() -> Self {
        #[derive(clap::Parser)]
        struct Bare {
            #[command(flatten)]
            options: PrecomputeOptions,
        }
        <Bare as clap::Parser>::try_parse_from(["translux-precompute"])
            .expect("the flags' defaults parse")
            .options
    }
}

impl PrecomputeOptions {
    /// The pipeline's settings: the flags checked (`--threshold`'s range and the dense F it
    /// needs, `--accuracy`, `--env-bins`) and `--subsurface auto` resolved. The error names
    /// the flag. `progress` is left off and `threads` unused: see
    /// [`PrecomputeOptions::build_global_thread_pool`].
    pub fn params(&self) -> Result<PrecomputeParams, String> {
        if !(self.threshold.is_finite() && (0.0..1.0).contains(&self.threshold)) {
            return Err(format!(
                "--threshold must be in [0, 1), got {}",
                self.threshold
            ));
        }
        let transport = match self.transport {
            Transport::Dense if self.links == Links::TwoSided => {
                return Err(
                    "--links two-sided links clusters of the hierarchical F; use it \
                            with --transport hierarchical"
                        .into(),
                );
            }
            Transport::Dense => FormFactorMethod::Dense,
            Transport::Hierarchical => {
                let hierarchy = HierarchyParams {
                    accuracy: self.accuracy,
                    two_sided: self.links == Links::TwoSided,
                    ..Default::default()
                };
                hierarchy.check()?;
                if self.threshold > 0.0 {
                    return Err("--threshold drops entries of a dense F; use it with \
                                --transport dense (a hierarchical F is bounded by --accuracy \
                                instead)"
                        .into());
                }
                FormFactorMethod::Hierarchical(hierarchy)
            }
        };
        let hierarchical_s = match self.subsurface {
            Subsurface::Auto => hierarchical_s_by_default(&transport, self.inverse),
            Subsurface::Pairwise => false,
            Subsurface::Hierarchical => true,
        };
        let subsurface_links = hierarchical_s.then(|| SLinkParams {
            accuracy: self.s_accuracy,
            near: self.s_link_near,
            tolerance: LinkTolerance {
                variation: self.s_link_variation,
                ..LinkTolerance::default()
            },
            ..SLinkParams::default()
        });
        let environment = match self.env_bins.as_deref() {
            None => EnvVisParams::default(),
            Some(text) => EnvVisParams {
                bins: parse_bins(text)?,
                ..Default::default()
            },
        };
        Ok(PrecomputeParams {
            patches: self.patches,
            max_edge: self.max_edge,
            form_factors: FormFactorParams {
                threshold: self.threshold,
                ..Default::default()
            },
            transport,
            memory_limit: self
                .max_memory_gib
                .map(|g| (g * (1u64 << 30) as f64) as u64),
            inverse: self.inverse,
            subsurface_links,
            environment,
            ..Default::default()
        })
    }

    /// `--threads`: sizes rayon's global pool (once per process, before any parallel work);
    /// without it, the pool keeps one thread per core.
    pub fn build_global_thread_pool(&self) -> Result<(), String> {
        let Some(t) = self.threads else {
            return Ok(());
        };
        rayon::ThreadPoolBuilder::new()
            .num_threads(t.max(1))
            .build_global()
            .map_err(|e| format!("setting up the thread pool: {e}"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_defaults_are_the_pipelines_with_auto_resolved() {
        let o = PrecomputeOptions::default();
        assert_eq!(o.transport, Transport::Hierarchical);
        assert_eq!(o.subsurface, Subsurface::Auto);
        let p = o.params().unwrap();
        assert_eq!(p.transport, FormFactorMethod::default());
        assert_eq!(p.subsurface_links, Some(SLinkParams::default()));
        assert_eq!(p.environment, EnvVisParams::default());
        assert!(!p.inverse && p.memory_limit.is_none() && p.patches.is_none());
    }

    #[test]
    fn auto_is_pairwise_with_t_or_a_dense_f() {
        for o in [
            PrecomputeOptions {
                inverse: true,
                ..Default::default()
            },
            PrecomputeOptions {
                transport: Transport::Dense,
                ..Default::default()
            },
            PrecomputeOptions {
                subsurface: Subsurface::Pairwise,
                ..Default::default()
            },
        ] {
            assert_eq!(o.params().unwrap().subsurface_links, None, "{o:?}");
        }
        let p = PrecomputeOptions {
            subsurface: Subsurface::Hierarchical,
            s_accuracy: 0.3,
            s_link_near: 1.5,
            s_link_variation: 0.5,
            ..Default::default()
        }
        .params()
        .unwrap();
        let sl = p.subsurface_links.unwrap();
        assert_eq!(
            (sl.accuracy, sl.near, sl.tolerance.variation),
            (0.3, 1.5, 0.5)
        );
    }

    #[test]
    fn bad_flags_are_refused_by_name() {
        for (o, says) in [
            (
                PrecomputeOptions {
                    threshold: f32::NAN,
                    ..Default::default()
                },
                "--threshold must be in [0, 1)",
            ),
            (
                PrecomputeOptions {
                    threshold: 0.01,
                    ..Default::default()
                },
                "use it with --transport dense",
            ),
            (
                PrecomputeOptions {
                    accuracy: 0.0,
                    ..Default::default()
                },
                "--accuracy must be in [0.02, 1]",
            ),
            (
                PrecomputeOptions {
                    env_bins: Some("ten".into()),
                    ..Default::default()
                },
                "",
            ),
            (
                PrecomputeOptions {
                    transport: Transport::Dense,
                    links: Links::TwoSided,
                    ..Default::default()
                },
                "--links two-sided links clusters of the hierarchical F",
            ),
        ] {
            let e = o.params().unwrap_err();
            assert!(e.contains(says), "{o:?}: {e}");
        }
        let dense = PrecomputeOptions {
            transport: Transport::Dense,
            threshold: 0.01,
            max_memory_gib: Some(2.0),
            env_bins: Some("0".into()),
            ..Default::default()
        }
        .params()
        .unwrap();
        assert_eq!(dense.form_factors.threshold, 0.01);
        assert_eq!(dense.memory_limit, Some(2 << 30));
        assert_eq!(dense.environment.bins, None);
    }
}
