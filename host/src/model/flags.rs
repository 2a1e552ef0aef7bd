//! The model flags, shared by every subcommand that builds a model (`deform model`,
//! `deform solve`, `simulate`, `observe`, `estimate`): flatten [`ModelFlags`] into a
//! subcommand's clap `Args`; [`crate::scenario::resolve_model`] merges them over a scenario file.
//!
//! Each flag value parses through the `FromStr` of its model type, so a malformed value is
//! refused by clap with the flag's name and the expected form; checks that need the whole
//! model (a node outside the grid, nothing fixed) happen in [`crate::model::Model::build`].
//! With no flags at all the spec is the thesis 2.6 example ([`ModelSpec::thesis_example`]).

use clap::{Args, ValueEnum};

use crate::model::{
    Connection, Elasticity, FacePressure, FixedNodeSet, Grid, ModelSpec, Node, PointLoad,
    PrescribedDisplacement,
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

/// Adds the thesis default load when nothing at all loads or moves the tissue.
fn with_default_load(mut spec: ModelSpec) -> ModelSpec {
    if spec.loads.is_empty() && spec.pressures.is_empty() && spec.prescribed.is_empty() {
        spec.loads = vec![ModelSpec::default_load(spec.grid)];
    }
    spec
}

/// The model flags of `deform solve` and `deform model`, which may also read a scenario file:
/// every flag is optional, and a flag that is given overrides the file, which overrides the
/// built-in defaults (the thesis 2.6 example). A list flag (--fix, --fix-node, --load,
/// --displace, --pressure) that is given replaces the file's list of that kind.
#[derive(Debug, Clone, Default, PartialEq, Args)]
pub struct ModelFlags {
    /// Nodes along x, y and z. Nodes are numbered x fastest, then y, then z:
    /// index = i + NX·(j + NY·k). At most 2^24 nodes in all. [default: 10,10,10]
    #[arg(
        help_heading = "Model",
        long,
        value_name = "NX,NY,NZ",
        allow_hyphen_values = true
    )]
    pub grid: Option<Grid>,

    /// Spring network: `a` joins each node to its 6 axial neighbours, `b` to all 26 neighbours
    /// (axial, edge and corner diagonals). [default: a]
    #[arg(
        help_heading = "Model",
        long = "model",
        value_name = "MODEL",
        value_enum
    )]
    pub connection: Option<ConnectionArg>,

    /// Homogeneous spring elasticity in N/m: one value K for every direction, or KX,KY,KZ for
    /// the x-, y- and z-displacement systems. Each must be finite and greater than 0. Replaces a
    /// scenario file's heterogeneous field. [default: 1,2,0.5]
    #[arg(
        help_heading = "Model",
        long = "k",
        value_name = "K|KX,KY,KZ",
        allow_hyphen_values = true
    )]
    pub elasticity: Option<Elasticity>,

    /// Node sets held at zero displacement, a comma-separated union of: `corners` (the 8
    /// corners), faces `x-`, `x+`, `y-`, `y+`, `z-`, `z+` (e.g. `x-` is every node with i = 0),
    /// or `none` (fix only the --fix-node nodes). At least one node must end up fixed or
    /// prescribed. [default: corners]
    #[arg(
        help_heading = "Model",
        long,
        value_name = "SETS",
        value_delimiter = ','
    )]
    pub fix: Option<Vec<FixedNodeSet>>,

    /// Also fix node (I,J,K), 0-based grid indices. Repeatable; adds to --fix. [default: none]
    #[arg(
        help_heading = "Model",
        long = "fix-node",
        value_name = "I,J,K",
        allow_hyphen_values = true
    )]
    pub fix_node: Vec<Node>,

    /// A point load: force (FX,FY,FZ) in N at node (I,J,K). Repeatable; loads at one node add
    /// up; loads on fixed or prescribed nodes are dropped. Default, if no load, pressure or
    /// displacement is given by flags or file: 1 N in +x at node (0, NY/2, NZ/2).
    #[arg(
        help_heading = "Model",
        long,
        value_name = "I,J,K:FX,FY,FZ",
        allow_hyphen_values = true
    )]
    pub load: Vec<PointLoad>,

    /// Prescribed displacement (UX,UY,UZ) of node (I,J,K), e.g. a needle tip pushing tissue.
    /// Repeatable. The node is held at exactly that value. [default: none]
    #[arg(
        help_heading = "Model",
        long,
        value_name = "I,J,K:UX,UY,UZ",
        allow_hyphen_values = true
    )]
    pub displace: Vec<PrescribedDisplacement>,

    /// A uniform face pressure: the total force (FX,FY,FZ) in N spread equally over the nodes
    /// of FACE (x-, x+, y-, y+, z-, z+). Repeatable. [default: none]
    #[arg(
        help_heading = "Model",
        long,
        value_name = "FACE:FX,FY,FZ",
        allow_hyphen_values = true
    )]
    pub pressure: Vec<FacePressure>,
}

impl ModelFlags {
    /// The spec these flags give over `file` (a scenario file's model, or `None` for the
    /// built-in defaults).
    pub fn spec_over(&self, file: Option<&ModelSpec>) -> ModelSpec {
        let mut spec = match file {
            Some(spec) => spec.clone(),
            None => ModelSpec {
                loads: Vec::new(),
                ..ModelSpec::thesis_example()
            },
        };
        if let Some(grid) = self.grid {
            spec.grid = grid;
        }
        if let Some(connection) = self.connection {
            spec.connection = connection.into();
        }
        if let Some(elasticity) = self.elasticity {
            spec.elasticity = elasticity;
            spec.field = None;
        }
        if let Some(fix) = &self.fix {
            spec.fixed_sets = fix.clone();
        }
        replace(&self.fix_node, &mut spec.fixed_nodes);
        replace(&self.load, &mut spec.loads);
        replace(&self.pressure, &mut spec.pressures);
        replace(&self.displace, &mut spec.prescribed);
        with_default_load(spec)
    }
}

fn replace<T: Clone>(given: &[T], target: &mut Vec<T>) {
    if !given.is_empty() {
        *target = given.to_vec();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::error::ErrorKind;
    use clap::Parser;

    fn parse(args: &[&str]) -> Result<ModelFlags, clap::Error> {
        let argv = std::iter::once("deform").chain(args.iter().copied());
        FlagsCli::try_parse_from(argv).map(|cli| cli.model)
    }

    fn error_text(args: &[&str]) -> String {
        let err = parse(args).unwrap_err();
        assert_eq!(err.kind(), ErrorKind::ValueValidation, "{err}");
        err.to_string()
    }

    #[derive(Debug, Parser)]
    struct FlagsCli {
        #[command(flatten)]
        model: ModelFlags,
    }

    fn flags(args: &[&str]) -> ModelFlags {
        let argv = std::iter::once("deform").chain(args.iter().copied());
        FlagsCli::try_parse_from(argv).unwrap().model
    }

    #[test]
    fn optional_flags_default_to_the_thesis_example_and_override_a_file() {
        assert_eq!(flags(&[]).spec_over(None), ModelSpec::thesis_example());
        let mut file = ModelSpec::thesis_example();
        file.grid = Grid::new(4, 4, 4).unwrap();
        file.field = Some(crate::model::NodeField::uniform(3.0));
        file.prescribed = vec!["1,1,3:0,0,-1".parse().unwrap()];
        file.loads = Vec::new();
        // No flags: the file as it is (no default load, since something moves the tissue).
        assert_eq!(flags(&[]).spec_over(Some(&file)), file);
        let spec =
            flags(&["--model", "b", "--k", "2", "--pressure", "z+:0,0,-1"]).spec_over(Some(&file));
        assert_eq!(spec.grid, file.grid);
        assert_eq!(spec.connection, Connection::AxialShear);
        assert_eq!(spec.field, None);
        assert_eq!(spec.elasticity, Elasticity::isotropic(2.0).unwrap());
        assert_eq!(spec.pressures.len(), 1);
        assert_eq!(spec.prescribed, file.prescribed);
        let spec = flags(&["--displace", "0,0,3:1,0,0", "--fix", "z-"]).spec_over(Some(&file));
        assert_eq!(spec.prescribed[0].node, Node::new(0, 0, 3));
        assert_eq!(spec.fixed_sets, vec!["z-".parse().unwrap()]);
    }

    #[test]
    fn no_flags_is_the_thesis_example() {
        let args = parse(&[]).unwrap();
        assert_eq!(args, ModelFlags::default());
        assert_eq!(args.spec_over(None), ModelSpec::thesis_example());
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
        let spec = args.spec_over(None);
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
        let spec = parse(&["--grid", "6,7,9"]).unwrap().spec_over(None);
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
        use crate::model::{Model, ModelError};
        trait Build {
            fn build(&self) -> Result<Model, ModelError>;
        }
        impl Build for ModelFlags {
            fn build(&self) -> Result<Model, ModelError> {
                Model::build(&self.spec_over(None))
            }
        }
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
