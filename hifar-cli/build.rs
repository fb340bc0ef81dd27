// The binary embeds CPython through pyo3. pyo3 links libpython but does not record where it
// lives, so a pyenv or /usr/local Python would not be found at run time without an rpath.
fn main() {
    let config = pyo3_build_config::get();
    if let Some(dir) = config.lib_dir() {
        println!("cargo:rustc-link-arg=-Wl,-rpath,{dir}");
    }
    println!("cargo:rerun-if-changed=build.rs");
}
