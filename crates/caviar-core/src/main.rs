//! `caviar-core` without Python: runs configurations made of built-in modules.
//! The binary installed with the Python package also hosts Python plugins.

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let code = caviar_core::cli::main(args, &caviar_core::run::BuiltinsOnly, &|| false);
    std::process::exit(code);
}
