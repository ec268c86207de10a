fn main() {
    println!("canopy: under construction");
}
