//! lpvid-host: the std companion of the `lpvid` core.
