"""Files and folders written safely: the one home of atomic writes, staged folders, output guards and locks.

- paths.py: a path a user gives, checked once (`check_path`, `user_path`) and shown safely (`shown_path`);
- atomic.py: atomic file writes (`replacing`, `atomic_open`, `atomic_write_text` / `_bytes`);
- jsonio.py: strict JSON / JSONL reading (`read_json`, `read_jsonl`) and JSON writing its reader accepts;
- folders.py: output folders written whole or not at all (`OutputKind`, `write_folder`, `check_target`);
- guard.py: no output replaces an input or a dataset file (`refuse_replacing_inputs`, `check_output_file`);
- locks.py: one writer at a time (`hold`); write_errors.py: a failed write as one line (`writing`);
- identity.py: a file's identity by its bytes or its size and time (`file_sha256`, `stat_tree`).

Standard library only; nothing here knows about datasets beyond their file names (guard.DATASET_FILES).
"""
