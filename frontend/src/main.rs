fn main() {
    spintune_web::start();
}
