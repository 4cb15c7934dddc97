//! Prophesee `% key value` header parsing and inference (to be implemented).
