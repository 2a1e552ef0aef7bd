//! The model flags, shared by every subcommand that builds a model (`deform model`,
//! `deform solve`): flatten [`ModelArgs`] into a subcommand's clap `Args` and call
//! [`ModelArgs::build`].
//!
//! Each flag value parses through the `FromStr` of its model type, so a malformed value is
//! refused by clap with the flag's name and the expected form; checks that need the whole
//! model (a node outside the grid, nothing fixed) happen in [`crate::model::Model::build`].
//! With no flags at all the spec is the thesis 2.6 example ([`ModelSpec::thesis_example`]).

use clap::{Args, ValueEnum};

use crate::model::{
    Connection, Elasticity, FixedNodeSet, Grid, Model, ModelError, ModelSpec, Node, PointLoad,
};

/// `--model`: the thesis's letters for the two spring networks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ConnectionArg {
    /// Model A (axial): springs to the 6 face neighbours; K has up to 7 nonzeros per row.
    A,
    /// Model B (axial-shear): springs to all 26 neighbours; K has up to 27 nonzeros per row.
    B,
}

impl From<ConnectionArg> for Connection {
    fn from(arg: ConnectionArg) -> Self {
        match arg {
            ConnectionArg::A => Connection::Axial,
            ConnectionArg::B => Connection::AxialShear,
        }
    }
}

/// The tissue model: grid, spring network, elasticity, fixed nodes and loads.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct ModelArgs {
    /// Nodes along x, y and z. Nodes are numbered x fastest, then y, then z:
    /// index = i + NX·(j + NY·k). At most 2^24 nodes in all.
    #[arg(
        help_heading = "Model",
        long,
        value_name = "NX,NY,NZ",
        default_value = "10,10,10",
        allow_hyphen_values = true
    )]
    pub grid: Grid,

    /// Spring network: `a` joins each node to its 6 axial neighbours, `b` to all 26 neighbours
    /// (axial, edge and corner diagonals).
    #[arg(help_heading = "Model", long = "model", value_name = "MODEL", value_enum, default_value_t = ConnectionArg::A)]
    pub connection: ConnectionArg,

    /// Spring elasticity in N/m: one value K for every direction, or KX,KY,KZ for the x-, y- and
    /// z-displacement systems. Each must be finite and greater than 0.
    #[arg(
        help_heading = "Model",
        long = "k",
        value_name = "K|KX,KY,KZ",
        default_value = "1,2,0.5",
        allow_hyphen_values = true
    )]
    pub elasticity: Elasticity,

    /// Node sets held at zero displacement, a comma-separated union of: `corners` (the 8
    /// corners), faces `x-`, `x+`, `y-`, `y+`, `z-`, `z+` (e.g. `x-` is every node with i = 0),
    /// or `none` (fix only the --fix-node nodes). At least one node must end up fixed.
    #[arg(
        long,
        value_name = "SETS",
        value_delimiter = ',',
        default_value = "corners"
    )]
    pub fix: Vec<FixedNodeSet>,

    /// Also fix node (I,J,K), 0-based grid indices. Repeatable; adds to --fix.
    #[arg(
        help_heading = "Model",
        long = "fix-node",
        value_name = "I,J,K",
        allow_hyphen_values = true
    )]
    pub fix_node: Vec<Node>,

    /// A point load: force (FX,FY,FZ) in N at node (I,J,K). Repeatable; loads at one node add
    /// up; loads on fixed nodes are dropped. Default (if no --load is given): 1 N in +x at the
    /// middle of the x = 0 face, node (0, NY/2, NZ/2) with integer division.
    #[arg(
        help_heading = "Model",
        long,
        value_name = "I,J,K:FX,FY,FZ",
        allow_hyphen_values = true
    )]
    pub load: Vec<PointLoad>,
}

impl Default for ModelArgs {
    /// The flags' defaults, i.e. what an empty command line gives.
    fn default() -> Self {
        let example = ModelSpec::thesis_example();
        Self {
            grid: example.grid,
            connection: ConnectionArg::A,
            elasticity: example.elasticity,
            fix: example.fixed_sets,
            fix_node: Vec::new(),
            load: Vec::new(),
        }
    }
}

impl ModelArgs {
    /// The model these flags describe.
    pub fn spec(&self) -> ModelSpec {
        let loads = if self.load.is_empty() {
            vec![ModelSpec::default_load(self.grid)]
        } else {
            self.load.clone()
        };
        ModelSpec {
            grid: self.grid,
            connection: self.connection.into(),
            elasticity: self.elasticity,
            fixed_sets: self.fix.clone(),
            fixed_nodes: self.fix_node.clone(),
            loads,
        }
    }

    /// Checks the flags together and assembles the model.
    pub fn build(&self) -> Result<Model, ModelError> {
        Model::build(&self.spec())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::error::ErrorKind;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct TestCli {
        #[command(flatten)]
        model: ModelArgs,
    }

    fn parse(args: &[&str]) -> Result<ModelArgs, clap::Error> {
        let argv = std::iter::once("deform").chain(args.iter().copied());
        TestCli::try_parse_from(argv).map(|cli| cli.model)
    }

    fn error_text(args: &[&str]) -> String {
        let err = parse(args).unwrap_err();
        assert_eq!(err.kind(), ErrorKind::ValueValidation, "{err}");
        err.to_string()
    }

    #[test]
    fn no_flags_is_the_thesis_example() {
        let args = parse(&[]).unwrap();
        assert_eq!(args, ModelArgs::default());
        assert_eq!(args.spec(), ModelSpec::thesis_example());
    }

    #[test]
    fn every_flag_reaches_the_spec() {
        let args = parse(&[
            "--grid",
            "4,5,6",
            "--model",
            "b",
            "--k",
            "3",
            "--fix",
            "x-,z+",
            "--fix",
            "corners",
            "--fix-node",
            "1,2,3",
            "--fix-node",
            "0,0,1",
            "--load",
            "1,1,1:0,0,-1",
            "--load",
            "2,2,2:1,0,0",
        ])
        .unwrap();
        let spec = args.spec();
        assert_eq!(spec.grid, Grid::new(4, 5, 6).unwrap());
        assert_eq!(spec.connection, Connection::AxialShear);
        assert_eq!(spec.elasticity, Elasticity::isotropic(3.0).unwrap());
        assert_eq!(
            spec.fixed_sets,
            ["x-", "z+", "corners"].map(|s| s.parse().unwrap()).to_vec()
        );
        assert_eq!(
            spec.fixed_nodes,
            vec![Node::new(1, 2, 3), Node::new(0, 0, 1)]
        );
        assert_eq!(spec.loads.len(), 2, "given loads replace the default one");
        assert_eq!(spec.loads[0].force, [0.0, 0.0, -1.0]);
    }

    #[test]
    fn default_load_follows_the_given_grid() {
        let spec = parse(&["--grid", "6,7,9"]).unwrap().spec();
        assert_eq!(spec.loads, vec![ModelSpec::default_load(spec.grid)]);
        assert_eq!(spec.loads[0].node, Node::new(0, 3, 4));
    }

    #[test]
    fn malformed_values_name_the_flag_and_the_expected_form() {
        let cases: &[(&[&str], &[&str])] = &[
            (&["--grid", "10,10"], &["--grid", "NX,NY,NZ"]),
            (&["--grid", "10,0,10"], &["--grid", "zero dimension"]),
            (&["--grid", "1000,1000,1000"], &["--grid", "limit"]),
            (&["--grid", "a,b,c"], &["--grid", "positive integer"]),
            (&["--k", "1,2"], &["--k", "KX,KY,KZ"]),
            (&["--k", "0"], &["--k", "greater than 0"]),
            (&["--k", "1,-2,3"], &["--k", "k_y"]),
            (&["--k", "-1"], &["--k", "k_x", "greater than 0"]),
            (&["--fix-node", "-1,0,0"], &["--fix-node", "non-negative"]),
            (&["--k", "1,inf,3"], &["--k", "finite"]),
            (&["--k", "soft"], &["--k", "not a number"]),
            (&["--fix", "corners,edges"], &["--fix", "'edges'", "x-"]),
            (&["--fix", ""], &["--fix"]),
            (&["--fix-node", "1,2"], &["--fix-node", "I,J,K"]),
            (&["--fix-node", "1,2,-1"], &["--fix-node", "non-negative"]),
            (&["--load", "1,2,3"], &["--load", "I,J,K:FX,FY,FZ"]),
            (&["--load", "1,2,3:1,0"], &["--load", "force part"]),
            (&["--load", "1,2:1,0,0"], &["--load", "node part"]),
            (&["--load", "1,2,3:nan,0,0"], &["--load", "not finite"]),
        ];
        for (args, needles) in cases {
            let text = error_text(args);
            for needle in *needles {
                assert!(text.contains(needle), "{args:?}: '{needle}' not in {text}");
            }
        }
        let err = parse(&["--model", "c"]).unwrap_err();
        assert_eq!(err.kind(), ErrorKind::InvalidValue);
        assert!(err.to_string().contains("--model"));
    }

    #[test]
    fn model_level_errors_come_from_build() {
        let outside = parse(&["--grid", "3,3,3", "--load", "3,0,0:1,0,0"]).unwrap();
        assert!(matches!(
            outside.build(),
            Err(ModelError::NodeOutsideGrid { .. })
        ));
        let outside = parse(&["--fix-node", "0,10,0"]).unwrap();
        assert!(matches!(
            outside.build(),
            Err(ModelError::NodeOutsideGrid { .. })
        ));
        let nothing_fixed = parse(&["--fix", "none"]).unwrap();
        assert_eq!(nothing_fixed.build().unwrap_err(), ModelError::NoFixedNode);
        let only_listed = parse(&["--fix", "none", "--fix-node", "0,0,0"]).unwrap();
        assert_eq!(only_listed.build().unwrap().fixed_count(), 1);
    }
}
