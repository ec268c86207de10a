//! Test certificates for the TLS suites (`transport/tests/tls.rs`, the multi-host tests of the
//! `tests` crate): a certificate authority and one certificate per zenoh user, made with the
//! `openssl` command (scripts/test.sh installs it on Debian). Not used by canopy itself: a
//! team's certificates come from its own CA (README, "TLS").

use std::path::Path;
use std::process::Command;

/// Makes a test certificate authority and one certificate per zenoh user in `dir` (created if
/// missing): EC P-256 keys (PKCS#8), CA `ca.pem` valid for 2 days; `USER.pem` / `USER.key`
/// with CN = USER, subject alternative names 127.0.0.1 and 127.0.0.2 (the loopback addresses
/// the multi-host tests use), for server and client authentication. `tag` names the CA (two
/// CAs must differ).
///
/// # Panics
/// If `openssl` cannot run or fails (its stderr in the message): a test without certificates
/// cannot go on.
pub fn make_certs(dir: &Path, tag: &str, users: &[&str]) {
    std::fs::create_dir_all(dir).expect("certificates directory");
    let openssl = |args: &[&str]| {
        let out = Command::new("openssl")
            .args(args)
            .current_dir(dir)
            .output()
            .unwrap_or_else(|e| {
                panic!("cannot run openssl ({e}): install it (scripts/test.sh does, from Debian)")
            });
        assert!(
            out.status.success(),
            "openssl {args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    };
    let ec = [
        "-newkey",
        "ec",
        "-pkeyopt",
        "ec_paramgen_curve:prime256v1",
        "-nodes",
    ];
    let subject = format!("/CN=canopy-test-ca-{tag}");
    let mut ca = vec!["req", "-x509"];
    ca.extend(ec);
    ca.extend([
        "-keyout",
        "ca.key",
        "-out",
        "ca.pem",
        "-days",
        "2",
        "-subj",
        &subject,
        "-addext",
        "basicConstraints=critical,CA:TRUE",
        "-addext",
        "keyUsage=critical,keyCertSign,cRLSign",
    ]);
    openssl(&ca);
    std::fs::write(
        dir.join("node.ext"),
        "basicConstraints=CA:FALSE\nsubjectAltName=IP:127.0.0.1,IP:127.0.0.2\n\
         extendedKeyUsage=serverAuth,clientAuth\n",
    )
    .expect("extensions file");
    for u in users {
        let (key, csr, pem, cn) = (
            format!("{u}.key"),
            format!("{u}.csr"),
            format!("{u}.pem"),
            format!("/CN={u}"),
        );
        let mut req = vec!["req"];
        req.extend(ec);
        req.extend(["-keyout", &key, "-out", &csr, "-subj", &cn]);
        openssl(&req);
        openssl(&[
            "x509",
            "-req",
            "-in",
            &csr,
            "-CA",
            "ca.pem",
            "-CAkey",
            "ca.key",
            "-CAcreateserial",
            "-out",
            &pem,
            "-days",
            "2",
            "-extfile",
            "node.ext",
        ]);
    }
}
