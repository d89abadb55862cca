"""Query registration: band, search, matching, acceptance, fusion, refinement, geolocation."""
