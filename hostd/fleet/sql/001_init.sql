-- min_client: 1
-- The central store of the display PCs' quality logs (docs/fleet.md). Applied by `hostd fleet
-- migrate` in one transaction, with its row in fleet.schema_version.
--
-- Roles: hostd_pc (NOLOGIN): every display PC's login role is a member, and its role name is its
-- pc_id; hostd_reader (NOLOGIN): the views' read-only role. Row-level security keys a PC's rows
-- on current_user: it inserts only rows with its own pc_id and reads only its own.
DO $$ BEGIN
    IF NOT EXISTS (SELECT FROM pg_roles WHERE rolname = 'hostd_pc') THEN
        CREATE ROLE hostd_pc NOLOGIN;
    END IF;
    IF NOT EXISTS (SELECT FROM pg_roles WHERE rolname = 'hostd_reader') THEN
        CREATE ROLE hostd_reader NOLOGIN;
    END IF;
END $$;

GRANT USAGE ON SCHEMA fleet TO hostd_pc, hostd_reader;
GRANT SELECT ON fleet.schema_version TO hostd_pc, hostd_reader;

-- the ledger of every row received: its uuid once, whatever partition the row went to (a unique
-- key of a partitioned table must hold its partition key, the server's receive time, and a row
-- sent again a month later would land in another partition). One index probe per row.
CREATE TABLE fleet.row_keys (
    uuid uuid PRIMARY KEY,
    pc_id text NOT NULL DEFAULT current_user,
    kind text NOT NULL CHECK (kind IN ('quality', 'play', 'health')),
    received_at timestamptz NOT NULL DEFAULT now()
);

-- every row: the PC (its role), the server's receive time (the partition key: never the PC's
-- clock), the PC's clock offset when it sent the row (PC minus server, s), the row's local id
CREATE TABLE fleet.quality (
    uuid uuid NOT NULL,
    pc_id text NOT NULL DEFAULT current_user,
    received_at timestamptz NOT NULL DEFAULT now(),
    pc_clock_offset_s double precision NOT NULL,
    local_id bigint NOT NULL,
    sha256 text NOT NULL,
    name text NOT NULL,
    pc_received_at timestamptz NOT NULL,
    scored_at timestamptz NOT NULL,
    bytes integer NOT NULL,
    method text NOT NULL,
    levels integer,
    b0_db double precision,
    n integer NOT NULL,
    n_keep integer NOT NULL,
    length_mm double precision NOT NULL,
    speed_mm_s double precision NOT NULL,
    curve_id text NOT NULL,
    ratio_coeffs double precision NOT NULL,
    ratio_profile double precision NOT NULL,
    ip double precision NOT NULL,
    ia double precision NOT NULL,
    iobj double precision NOT NULL,
    a double precision NOT NULL,
    b double precision NOT NULL,
    calibration text,
    PRIMARY KEY (uuid, received_at)
) PARTITION BY RANGE (received_at);

CREATE TABLE fleet.plays (
    uuid uuid NOT NULL,
    pc_id text NOT NULL DEFAULT current_user,
    received_at timestamptz NOT NULL DEFAULT now(),
    pc_clock_offset_s double precision NOT NULL,
    local_id bigint NOT NULL,
    name text NOT NULL,
    sha256 text NOT NULL,
    started_at timestamptz NOT NULL,
    ended_at timestamptz NOT NULL,
    device_s double precision NOT NULL,
    played_s double precision NOT NULL,
    played_fraction double precision,
    underruns bigint NOT NULL,
    PRIMARY KEY (uuid, received_at)
) PARTITION BY RANGE (received_at);

-- a device-health summary, taken by the shipper from the daemon's status
CREATE TABLE fleet.health (
    uuid uuid NOT NULL,
    pc_id text NOT NULL DEFAULT current_user,
    received_at timestamptz NOT NULL DEFAULT now(),
    pc_clock_offset_s double precision NOT NULL,
    taken_at timestamptz NOT NULL,
    serial text,
    firmware text,
    transport text,
    device_state text,
    device_underruns bigint,
    played_fraction double precision,
    stalls bigint,
    recoveries bigint,
    waiting_rows bigint,
    waiting_since timestamptz,
    PRIMARY KEY (uuid, received_at)
) PARTITION BY RANGE (received_at);

-- the views' questions: per display over time, per texture over time
CREATE INDEX quality_pc_time ON fleet.quality (pc_id, received_at);
CREATE INDEX quality_sha ON fleet.quality (sha256);
CREATE INDEX plays_pc_time ON fleet.plays (pc_id, received_at);
CREATE INDEX health_pc_time ON fleet.health (pc_id, received_at);

-- the current month's partition and the next one's: called by every shipper when it connects
-- and each hour (SECURITY DEFINER: the table owner creates them, a PC cannot create tables)
CREATE FUNCTION fleet.ensure_partitions() RETURNS void LANGUAGE plpgsql SECURITY DEFINER
SET search_path = pg_catalog, fleet AS $$
DECLARE
    m timestamptz;
    t text;
BEGIN
    FOREACH t IN ARRAY ARRAY['quality', 'plays', 'health'] LOOP
        FOR i IN 0..1 LOOP
            m := date_trunc('month', now() AT TIME ZONE 'UTC') AT TIME ZONE 'UTC' + make_interval(months => i);
            IF to_regclass(format('fleet.%s_%s', t, to_char(m AT TIME ZONE 'UTC', 'YYYYMM'))) IS NULL THEN
                PERFORM pg_advisory_xact_lock(hashtext('fleet.ensure_partitions'));
                EXECUTE format('CREATE TABLE IF NOT EXISTS fleet.%I PARTITION OF fleet.%I '
                               'FOR VALUES FROM (%L) TO (%L)', t || '_' || to_char(m AT TIME ZONE 'UTC', 'YYYYMM'),
                               t, m, m + interval '1 month');
            END IF;
        END LOOP;
    END LOOP;
END $$;
REVOKE ALL ON FUNCTION fleet.ensure_partitions() FROM PUBLIC;
GRANT EXECUTE ON FUNCTION fleet.ensure_partitions() TO hostd_pc;
SELECT fleet.ensure_partitions();

ALTER TABLE fleet.row_keys ENABLE ROW LEVEL SECURITY;
ALTER TABLE fleet.quality ENABLE ROW LEVEL SECURITY;
ALTER TABLE fleet.plays ENABLE ROW LEVEL SECURITY;
ALTER TABLE fleet.health ENABLE ROW LEVEL SECURITY;
DO $$
DECLARE
    t text;
BEGIN
    FOREACH t IN ARRAY ARRAY['row_keys', 'quality', 'plays', 'health'] LOOP
        EXECUTE format('CREATE POLICY pc_insert ON fleet.%I FOR INSERT TO hostd_pc '
                       'WITH CHECK (pc_id = current_user)', t);
        EXECUTE format('CREATE POLICY pc_select ON fleet.%I FOR SELECT TO hostd_pc '
                       'USING (pc_id = current_user)', t);
        EXECUTE format('CREATE POLICY reader_select ON fleet.%I FOR SELECT TO hostd_reader USING (true)', t);
        -- a PC inserts and reads its own rows; it never updates or deletes one (no grant)
        EXECUTE format('GRANT INSERT, SELECT ON fleet.%I TO hostd_pc', t);
        EXECUTE format('GRANT SELECT ON fleet.%I TO hostd_reader', t);
    END LOOP;
END $$;
