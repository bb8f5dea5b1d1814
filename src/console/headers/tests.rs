use super::*;

#[test]
fn hsts_under_tls_only_and_the_usual_headers_always() {
    for https in [false, true] {
        let mut h = axum::http::HeaderMap::new();
        add_headers(&mut h, https, true);
        assert_eq!(h.contains_key(header::STRICT_TRANSPORT_SECURITY), https);
        for name in [
            "content-security-policy",
            "x-content-type-options",
            "x-frame-options",
            "referrer-policy",
            "cross-origin-opener-policy",
            "cross-origin-resource-policy",
            "cache-control",
        ] {
            assert!(h.contains_key(name), "{name}");
        }
    }
}
