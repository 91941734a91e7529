fn main() -> std::process::ExitCode {
    match rigd::cli::main() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("rigctl: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
